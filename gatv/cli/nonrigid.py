"""``gatv nonrigid SOURCE TARGET``: a locally rigid, non-rigid motion (:func:`gatv.nonrigid.register`),
or with ``--segment`` every non-rigid motion (:func:`gatv.nonrigid.segment`)."""

from __future__ import annotations

import sys
import time

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    POINT_FILES,
    PROG,
    add_noise,
    add_outputs,
    add_point_files,
    add_seed,
    add_verbosity,
    check_outputs,
    guarded,
    result_record,
    write_outputs,
)

__all__ = ["NAME", "add_parser", "render", "run"]

NAME = "nonrigid"


def add_parser(subparsers):
    """Add the ``nonrigid`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="find a non-rigid (locally rigid) motion taking SOURCE onto TARGET",
        description=(
            "Find one-to-one correspondences and a smooth warp taking SOURCE onto TARGET under a "
            "locally rigid, non-rigid motion (section 5.1), with no initial guess. Point files: "
            f"{POINT_FILES}."
        ),
    )
    add_point_files(p)
    add_outputs(p)
    add_seed(p, "the registration")
    p.add_argument("--max-displacement", type=float, metavar="DIST",
                   help="bound on how far a point moves, data units")
    add_noise(p)
    p.add_argument("--prealign", choices=("auto", "always", "never"), default="auto",
                   help="start a coarse-to-fine hypothesis from the dominant rigid motion: "
                        "auto (only when nothing else beats chance, bounded search), always, never "
                        "(default: auto)")
    p.add_argument("--segment", action="store_true",
                   help="find several non-rigid motions (their number unknown) with per-point labels")
    add_verbosity(p, progress=False)
    p.set_defaults(handler=run)
    return p


def render(source, target, motion, path) -> None:
    """Write the picture of a non-rigid registration: target, warped source, correspondences."""
    import numpy as np

    from .. import render as rd

    plotter = rd.new_plotter((1200, 800))
    try:
        rd.add_points(plotter, target, color=rd.PALETTE[0], size=6, label="target")
        rd.add_points(plotter, motion.warp(source), color=rd.PALETTE[1], size=6,
                      label="source, warped")
        if motion.support:
            rd.add_correspondences(plotter, np.asarray(source), np.asarray(target),
                                   motion.correspondences)
        rd.add_title(plotter, f"{motion.support} correspondences (non-rigid)")
        rd.save(plotter, path)
    finally:
        plotter.close()


@guarded
def run(args) -> int:
    """Run ``gatv nonrigid`` on parsed ``args``; return the exit status."""
    from ..io import read_points, write_json
    from ..nonrigid import register, segment

    check_outputs(args, inputs=(args.source, args.target))
    source = read_points(args.source)
    target = read_points(args.target)
    options = {}
    if args.max_displacement is not None:
        options["max_displacement"] = args.max_displacement
    if args.noise is not None:
        options["noise"] = args.noise
    options["prealign"] = {"auto": "auto", "always": True, "never": False}[args.prealign]
    start = time.perf_counter()
    if getattr(args, "segment", False):
        return _run_segment(args, source, target, options, segment)
    motion = register(source, target, seed=args.seed, **options)
    seconds = time.perf_counter() - start
    ok = bool(motion)
    if not args.quiet:
        print(f"correspondences: {motion.support}")
        print(f"time:            {seconds:.3f} s")
        print(f"hypothesis:      {motion.info.get('hypothesis')}")
    if not ok:
        print(f"{PROG}: registration failed: {motion.info.get('reason', 'nothing found')}", file=sys.stderr)
    inputs = {"source": str(args.source), "target": str(args.target)}
    record = result_record(inputs, source, target, seed=args.seed, options=options,
                           seconds=seconds, result=motion)
    write_outputs([
        (args.out, lambda tmp: write_json(tmp, record)),
        (args.render if ok else None, lambda tmp: render(source, target, motion, tmp)),
    ], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED


def _run_segment(args, source, target, options, segment) -> int:
    """``gatv nonrigid --segment``: print each motion, write the JSON record (labels included)."""
    import numpy as np

    from ..io import write_json

    start = time.perf_counter()
    result = segment(source, target, seed=args.seed, **options)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"motions:         {len(result)}")
        for k, m in enumerate(result.motions):
            print(f"motion {k}:        {m.support} correspondences")
        print(f"unexplained:     {int(np.sum(result.source_labels < 0))} source, "
              f"{int(np.sum(result.target_labels < 0))} target points")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: segmentation found no non-rigid motion: "
              f"{result.info.get('reason', 'nothing found')}", file=sys.stderr)
    inputs = {"source": str(args.source), "target": str(args.target)}
    record = result_record(inputs, source, target, seed=args.seed, options=dict(options, segment=True),
                           seconds=seconds, result=result)
    write_outputs([(args.out, lambda tmp: write_json(tmp, record))], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
