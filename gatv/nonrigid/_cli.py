"""``gatv nonrigid SOURCE TARGET``: the command-line face of :mod:`gatv.nonrigid`.

Wired into :mod:`gatv.cli` by ``add_parser(subparsers)``; ``run(args)``
returns the exit status with the conventions of ``gatv register``: 0 on
success, 1 when nothing was found, 2 on bad input (one line
``gatv: error: <message>`` on stderr, no traceback), and no output file
unless every output could be written (temporary files moved into place at
the end).
"""

from __future__ import annotations

import contextlib
import sys
import time
from pathlib import Path

from gatv.cli import (  # one set of conventions for every subcommand
    EXIT_FAILED,
    EXIT_OK,
    EXIT_USAGE,
    PROG,
    _check_outputs,
    _error,
    _one_line,
)

from ..errors import InputError

__all__ = ["add_parser", "run"]


def add_parser(subparsers):
    """Add the ``nonrigid`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "nonrigid",
        help="find a non-rigid (locally rigid) motion taking SOURCE onto TARGET",
        description=(
            "Find one-to-one correspondences and a smooth warp taking SOURCE onto TARGET under a "
            "locally rigid, non-rigid motion (section 5.1), with no initial guess. Point files: "
            ".ply .vtk .vtp .stl .obj .xyz .txt .csv .pts .npy."
        ),
    )
    p.add_argument("source", type=Path, help="source point file")
    p.add_argument("target", type=Path, help="target point file")
    p.add_argument("--out", type=Path, metavar="JSON", help="write the result as JSON")
    p.add_argument("--render", type=Path, metavar="PNG", help="write an off-screen picture")
    p.add_argument("--seed", type=int, default=0, help="seed of the registration (default: 0)")
    p.add_argument("--max-displacement", type=float, metavar="DIST",
                   help="bound on how far a point moves, data units")
    p.add_argument("--noise", type=float, metavar="SIGMA", help="point noise, data units")
    p.add_argument("--prealign", choices=("auto", "always", "never"), default="auto",
                   help="start a coarse-to-fine hypothesis from the dominant rigid motion: "
                        "auto (only when nothing else beats chance, bounded search), always, never "
                        "(default: auto)")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    p.set_defaults(handler=run)
    return p


def _render(source, target, motion, path) -> None:
    import numpy as np

    from .. import render

    plotter = render.new_plotter((1200, 800))
    try:
        render.add_points(plotter, target, color=render.PALETTE[0], size=6, label="target")
        render.add_points(plotter, motion.warp(source), color=render.PALETTE[1], size=6,
                          label="source, warped")
        if motion.support:
            render.add_correspondences(plotter, np.asarray(source), np.asarray(target),
                                       motion.correspondences)
        render.add_title(plotter, f"{motion.support} correspondences (non-rigid)")
        render.save(plotter, path)
    finally:
        plotter.close()


def _run(args) -> int:
    from ..io import atomic_path, read_points, to_jsonable, write_json
    from .registration import register

    outs = _check_outputs(args)
    source = read_points(args.source)
    target = read_points(args.target)
    for out in outs:
        if out in (args.source.resolve(), args.target.resolve()):
            raise InputError(f"{out}: refusing to overwrite an input file.")
    options = {}
    if args.max_displacement is not None:
        options["max_displacement"] = args.max_displacement
    if args.noise is not None:
        options["noise"] = args.noise
    options["prealign"] = {"auto": "auto", "always": True, "never": False}[args.prealign]
    start = time.perf_counter()
    motion = register(source, target, seed=args.seed, **options)
    seconds = time.perf_counter() - start
    ok = bool(motion)
    if not args.quiet:
        print(f"correspondences: {motion.support}")
        print(f"time:            {seconds:.3f} s")
        print(f"hypothesis:      {motion.info.get('hypothesis')}")
    if not ok:
        print(f"{PROG}: registration failed: {motion.info.get('reason', 'nothing found')}", file=sys.stderr)
    record = {
        "source": str(args.source), "target": str(args.target),
        "n_source": int(len(source)), "n_target": int(len(target)),
        "seed": args.seed, "options": options, "success": ok, "time_s": seconds,
        **motion.to_dict(), "info": to_jsonable(motion.info),
    }
    with contextlib.ExitStack() as stack:  # all outputs land together, or none
        if args.out is not None:
            write_json(stack.enter_context(atomic_path(args.out)), record)
        if ok and args.render is not None:
            _render(source, target, motion, stack.enter_context(atomic_path(args.render)))
    if not args.quiet:
        for path in (args.out, args.render if ok else None):
            if path is not None:
                print(f"wrote {path}")
    return EXIT_OK if ok else EXIT_FAILED


def run(args) -> int:
    """Run ``gatv nonrigid`` on parsed ``args``; return the exit status."""
    import os

    try:
        return _run(args)
    except (ValueError, OSError) as exc:
        if os.environ.get("GATV_DEBUG"):
            raise
        _error(_one_line(exc))
        return EXIT_USAGE
