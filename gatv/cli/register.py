"""``gatv register SOURCE TARGET``: the motion taking SOURCE onto TARGET (:func:`gatv.register`).

Also home of :func:`register_and_write`, the registration step ``gatv demo``
shares.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    POINT_FILES,
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
from .warmup import compile_notes

__all__ = [
    "NAME",
    "add_parser",
    "add_run_options",
    "load_register",
    "register_and_write",
    "render",
    "run",
    "summary",
]

NAME = "register"


def add_parser(subparsers):
    """Add the ``register`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="find the motion taking SOURCE onto TARGET",
        description=(
            "Find the motion taking SOURCE onto TARGET (rigid: target = R source + t) and their "
            "correspondences, with no initial guess. Point files: "
            f"{POINT_FILES}."
        ),
    )
    add_point_files(p)
    p.add_argument(
        "--pipeline", choices=("auto", "exact", "scans"), default=None,
        help="exact: congruent triples on the points themselves; scans: dense, differently sampled "
             "range scans (surface tokens, voxel downsampling, normal-pruned trials, point-to-plane "
             "polish at full resolution); auto (default): chosen from the data",
    )
    p.add_argument("--scans", action="store_true", help="the same as --pipeline scans")
    add_model(p)
    add_run_options(p)
    p.set_defaults(handler=run)
    return p


def add_run_options(p) -> None:
    """The outputs and options of a registration (``register`` and ``demo``)."""
    add_outputs(p, aligned=True)
    p.add_argument("--matrix", type=Path, metavar="FILE",
                   help="write the motion as a 4x4 matrix, four lines of text (numpy.loadtxt, Open3D)")
    add_seed(p, "the registration")
    p.add_argument(
        "--max-angle", type=float, metavar="DEG",
        help="bound on the rotation angle in degrees (small-motion mode)",
    )
    p.add_argument(
        "--max-translation", type=float, metavar="DIST",
        help="bound on |t| in data units (with --max-angle)",
    )
    add_noise(p)
    p.add_argument(
        "--time-limit", type=float, metavar="SECONDS",
        help="wall-clock bound on the exact search (default: 60); past it the call fails with its reason",
    )
    add_verbosity(p)


def load_register():
    """:func:`gatv.register`; RuntimeError if it cannot be imported."""
    from ..io import one_line

    try:
        from ..registration import register
    except ImportError as exc:
        msg = f"the registration module gatv.registration cannot be imported ({one_line(exc)})."
        raise RuntimeError(msg) from exc
    return register


def render(source, target, motion, path) -> None:
    """Write the picture of a registration (:func:`gatv.render.render_registration`)."""
    from ..render import render_registration

    render_registration(source, target, motion, path)


def summary(motion, seconds: float) -> list[str]:
    """The lines printed for a registration result."""
    lines = [f"model:           {getattr(motion, 'model', '') or type(motion).__name__}"]
    lines += [f"{label + ':':<17}{text}" for label, text in motion_lines(motion)]
    lines.append(f"correspondences: {motion.support}")
    lines.append(f"rms:             {motion.rms:.6g}")
    if motion.info.get("ambiguous"):
        angle = (motion.info.get("rival") or {}).get("angle_deg")
        away = f" {angle:.0f} deg away" if angle is not None else ""
        lines.append(f"ambiguous:       a distinct motion{away} fits nearly as well (a symmetric object?)")
    lines.append(f"time:            {seconds:.3f} s")
    return lines


def _options(args) -> dict:
    names = ("max_angle", "max_translation", "noise", "time_limit")
    opts = {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
    opts.update(model_options(args))
    return opts


def _pipeline(args) -> str:
    """``--pipeline`` and its shorthand ``--scans``, which must agree."""
    chosen = getattr(args, "pipeline", None)
    if getattr(args, "scans", False):
        if chosen not in (None, "scans"):
            raise UsageError(f"--scans contradicts --pipeline {chosen}; give one of them.")
        chosen = "scans"
    return chosen or "auto"


def register_and_write(args, source, target, inputs: dict, extra: dict | None = None):
    """Register, print, and write every output atomically; return ``(status, motion)``."""
    from ..io import write_json, write_matrix, write_points

    check_point_counts((name, pts, inputs[name]) for name, pts in (("source", source), ("target", target)))
    pipeline = _pipeline(args)
    register = load_register()
    options = _options(args)
    if pipeline == "scans" and options:
        raise UsageError(f"--scans takes no {', '.join('--' + k.replace('_', '-') for k in options)}.")
    progress = progress_printer(args)
    call = dict(options)
    if pipeline != "auto":
        call["pipeline"] = pipeline
    start = time.perf_counter()
    with compile_notes(progress, quiet=args.quiet, ahead=True) as notes:
        if notes.progress is not None:
            call["progress"] = notes.progress
        motion = register(source, target, seed=args.seed, **call)
    seconds = time.perf_counter() - start

    ok = bool(motion)
    if not args.quiet:
        for line in summary(motion, seconds):
            print(line)
    if not ok:
        reason = motion.info.get("reason", "no motion found") if hasattr(motion, "info") else "no motion found"
        print(f"{PROG}: registration failed: {reason}", file=sys.stderr)

    record = result_record(inputs, source, target, seed=args.seed, options=options,
                           seconds=seconds, result=motion)
    if extra:
        record.update(extra)
    aligned = args.aligned if ok else None
    write_outputs([
        (args.out, lambda tmp: write_json(tmp, record)),
        (aligned, lambda tmp: write_points(tmp, motion.transform(source))),
        (args.render if ok else None, lambda tmp: render(source, target, motion, tmp)),
        (getattr(args, "matrix", None) if ok else None, lambda tmp: write_matrix(tmp, motion.matrix)),
    ], quiet=args.quiet)
    return (EXIT_OK if ok else EXIT_FAILED), motion


@guarded
def run(args) -> int:
    """Run ``gatv register`` on parsed ``args``; return the exit status."""
    from ..io import read_points

    check_outputs(args, inputs=(args.source, args.target))
    model_options(args)  # a model of 2D points is refused before reading
    source = read_points(args.source)
    target = read_points(args.target)
    inputs = {"source": str(args.source), "target": str(args.target)}
    return register_and_write(args, source, target, inputs)[0]


