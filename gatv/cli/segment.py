"""``gatv segment SOURCE TARGET``: every motion between SOURCE and TARGET (:func:`gatv.motions.segment`)."""

from __future__ import annotations

import sys
import time

import numpy as np

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    PROG,
    UsageError,
    add_model,
    add_noise,
    add_outputs,
    add_point_files,
    add_seed,
    add_verbosity,
    check_outputs,
    check_point_counts,
    guarded,
    model_options,
    motion_lines,
    progress_printer,
    result_record,
    write_outputs,
)

__all__ = ["NAME", "add_parser", "load_segment", "render_segmentation", "run"]

NAME = "segment"


def add_parser(subparsers):
    """Add the ``segment`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="find every motion between SOURCE and TARGET (several overlapping motions)",
        description=(
            "Find every motion taking part of SOURCE onto part of TARGET (paper section 5), "
            "each with its own one-to-one correspondences; each point belongs to at most one "
            "motion. The number of motions is found from the data."
        ),
    )
    add_point_files(p)
    add_model(p)
    add_outputs(p, render="write an off-screen picture, one colour per motion")
    add_seed(p, "the trial search")
    p.add_argument("--max-motions", type=int, metavar="K", help="return at most K motions (largest first)")
    p.add_argument("--min-support", type=int, metavar="N",
                   help="correspondences a motion needs (default: from the chance level)")
    add_noise(p)
    add_verbosity(p)
    p.set_defaults(handler=run)
    return p


def load_segment():
    """:func:`gatv.motions.segment`; RuntimeError if it cannot be imported."""
    from ..io import one_line

    try:
        from ..motions import segment
    except ImportError as exc:
        msg = f"the segmentation module gatv.motions cannot be imported ({one_line(exc)})."
        raise RuntimeError(msg) from exc
    return segment


def render_segmentation(source, target, segmentation, path) -> None:
    """Write the picture of a segmentation (:func:`gatv.render.render_segmentation`)."""
    from ..render import render_segmentation as render

    render(source, target, segmentation, path)


def _describe(motion) -> str:
    parts = []
    for label, text in motion_lines(motion):
        parts.append(text if label == "rotation" else f"{'t' if label == 'translation' else label} = {text}")
    return ", ".join(parts)


@guarded
def run(args) -> int:
    """Run ``gatv segment`` on parsed ``args``; return the exit status."""
    from ..io import read_points, write_json

    check_outputs(args, inputs=(args.source, args.target))
    if args.max_motions is not None and args.max_motions < 1:
        raise UsageError(f"expected --max-motions >= 1, got {args.max_motions}.")
    source = read_points(args.source)
    target = read_points(args.target)
    check_point_counts((("source", source, args.source), ("target", target, args.target)))
    segment = load_segment()

    options = {k: v for k, v in (("max_motions", args.max_motions), ("min_support", args.min_support),
                                 ("noise", args.noise)) if v is not None}
    options.update(model_options(args))
    progress = progress_printer(args)
    start = time.perf_counter()
    result = segment(source, target, seed=args.seed, progress=progress, **options)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"model:           {args.model}")
        print(f"motions:         {len(result)}")
        for k, m in enumerate(result.motions):
            print(f"motion {k}:        {_describe(m)}, {m.support} correspondences, rms {m.rms:.3g}")
        print(f"unexplained:     {int(np.sum(result.source_labels < 0))} source, "
              f"{int(np.sum(result.target_labels < 0))} target points")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: segmentation found no motion: "
              f"{result.info.get('reason', 'no plane with enough support')}", file=sys.stderr)
    inputs = {"source": str(args.source), "target": str(args.target)}
    record = result_record(inputs, source, target, seed=args.seed, options=options,
                           seconds=seconds, result=result)
    write_outputs([
        (args.out, lambda tmp: write_json(tmp, record)),
        (args.render if ok else None, lambda tmp: render_segmentation(source, target, result, tmp)),
    ], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
