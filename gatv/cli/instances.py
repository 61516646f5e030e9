"""``gatv instances MODEL SCENE``: every copy of MODEL in SCENE (:func:`gatv.motions.instances`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    POINT_FILES,
    PROG,
    UsageError,
    add_seed,
    add_verbosity,
    check_outputs,
    check_point_counts,
    guarded,
    motion_lines,
    progress_printer,
    result_record,
    write_outputs,
)
from .segment import LABELLED_EXTENSIONS, write_labelled
from .warmup import compile_notes

__all__ = ["NAME", "add_instance_options", "add_parser", "check_labelled", "describe", "instance_options",
           "load_instances", "run"]

NAME = "instances"


def add_parser(subparsers):
    """Add the ``instances`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="find every copy of MODEL in SCENE (their number unknown)",
        description=(
            "Find every copy of MODEL in SCENE, whole or partial, among clutter (paper section 4.1): "
            "each a rigid motion from MODEL to SCENE with its correspondences, kept only when it beats "
            "the wrong motions. MODEL points may serve every copy; each SCENE point belongs to at most "
            f"one. Point files: {POINT_FILES}."
        ),
    )
    p.add_argument("model", type=Path, help=f"model point file ({POINT_FILES})")
    p.add_argument("scene", type=Path, help="scene point file (the same formats)")
    p.add_argument("--out", type=Path, metavar="JSON", help="write the result as JSON")
    p.add_argument("--render", type=Path, metavar="PNG",
                   help="write an off-screen picture, one colour per instance")
    p.add_argument("--labelled", type=Path, metavar="PLY",
                   help="write the scene points with a per-point `motion` scalar, the instance "
                        "(-1: none; .ply .vtk .vtp)")
    add_instance_options(p)
    p.set_defaults(handler=run)
    return p


def add_instance_options(p) -> None:
    """The options ``instances`` and ``track`` share."""
    add_seed(p, "the search")
    p.add_argument("--max-instances", type=int, metavar="K", help="stop after K instances")
    p.add_argument(
        "--pipeline", choices=("auto", "exact", "scans"), default="auto",
        help="exact: point sets whose inliers are the same points in MODEL and SCENE (noisy or not); "
             "scans: dense, differently sampled range scans; auto: chosen from the data (default)")
    p.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="wall-clock bound on the search of one scene (default: 600); past it the "
                        "instances found so far are returned, with the reason")
    add_verbosity(p)


def instance_options(args) -> dict:
    """The keyword options of ``--max-instances``, ``--pipeline`` and ``--time-limit`` (those given)."""
    if args.max_instances is not None and args.max_instances < 1:
        raise UsageError(f"expected --max-instances >= 1, got {args.max_instances}.")
    if args.time_limit is not None and not args.time_limit > 0:
        raise UsageError(f"expected --time-limit > 0, got {args.time_limit}.")
    options = {k: v for k, v in (("max_instances", args.max_instances), ("time_limit", args.time_limit))
               if v is not None}
    if args.pipeline != "auto":
        options["pipeline"] = args.pipeline
    return options


def load_instances():
    """:func:`gatv.motions.instances`; RuntimeError if it cannot be imported."""
    from ..io import one_line

    try:
        from ..motions import instances
    except ImportError as exc:
        msg = f"the instance search gatv.motions cannot be imported ({one_line(exc)})."
        raise RuntimeError(msg) from exc
    return instances


def check_labelled(path, others) -> None:
    """``--labelled``: a labelled-point extension, an existing folder, a file of its own."""
    if path is None:
        return
    if path.suffix.lower() not in LABELLED_EXTENSIONS:
        raise UsageError(f"{path}: cannot write labelled points as {path.suffix or 'a file without extension'!r}; "
                         f"expected one of {', '.join(LABELLED_EXTENSIONS)}.")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise UsageError(f"{path}: cannot write labelled points: folder {str(folder)!r} does not exist.")
    if path.resolve() in [Path(x).resolve() for x in others if x is not None]:
        raise UsageError(f"{path}: --labelled must name a file of its own (not an input or another output).")


def describe(motion) -> str:
    """One line of an instance: its rotation, translation, support and rms."""
    parts = []
    for label, text in motion_lines(motion):
        parts.append(text if label == "rotation" else f"{'t' if label == 'translation' else label} = {text}")
    return f"{', '.join(parts)}, {motion.support} correspondences, rms {motion.rms:.3g}"


def _render(model, scene, found, path) -> None:
    from ..render import render_motions

    render_motions(model, scene, tuple(found.instances), path)


@guarded
def run(args) -> int:
    """Run ``gatv instances`` on parsed ``args``; return the exit status."""
    from ..io import read_points, write_json

    check_outputs(args, inputs=(args.model, args.scene))
    check_labelled(args.labelled, (args.out, args.render, args.model, args.scene))
    options = instance_options(args)
    model = read_points(args.model)
    scene = read_points(args.scene)
    check_point_counts((("model", model, args.model),), minimum=4)
    check_point_counts((("scene", scene, args.scene),))
    instances = load_instances()
    progress = progress_printer(args)
    start = time.perf_counter()
    with compile_notes(progress, quiet=args.quiet, ahead=True) as notes:
        found = instances(model, scene, seed=args.seed, progress=notes.progress, **options)
    seconds = time.perf_counter() - start
    ok = bool(found)
    if not args.quiet:
        print(f"instances:       {len(found)}")
        for k, m in enumerate(found):
            print(f"instance {k}:      {describe(m)}")
        print(f"unexplained:     {int(np.sum(found.labels < 0))} scene points")
        print(f"pipeline:        {found.info['pipeline']} ({found.info.get('pipeline_reason', '')})")
        print(f"stopped:         {found.info['reason']}")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: no instance of the model found: {found.info.get('reason', '')}", file=sys.stderr)
    record = result_record({"model": str(args.model), "scene": str(args.scene)}, model, scene, seed=args.seed,
                           options=options, seconds=seconds, result=found)
    write_outputs([
        (args.out, lambda tmp: write_json(tmp, record)),
        (args.render if ok else None, lambda tmp: _render(model, scene, found, tmp)),
        (args.labelled, lambda tmp: write_labelled(tmp, scene, found.labels)),
    ], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
