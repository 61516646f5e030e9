"""``gatv track MODEL FRAME...``: every copy of MODEL in each frame, identities kept (:func:`gatv.motions.track`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    POINT_FILES,
    PROG,
    check_outputs,
    check_point_counts,
    guarded,
    progress_printer,
    write_outputs,
)
from .instances import add_instance_options, describe, instance_options
from .warmup import compile_notes

__all__ = ["NAME", "add_parser", "load_track", "run"]

NAME = "track"


def add_parser(subparsers):
    """Add the ``track`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="find every copy of MODEL in each FRAME, identities kept by the closest pose",
        description=(
            "Find every copy of MODEL in each FRAME on its own (no motion model between frames, as in the "
            "paper's section 4.1: 'this is not a video'), then give the copies of consecutive frames "
            "identities by the closest pose. A copy missing from a frame is reported there. Point files: "
            f"{POINT_FILES}."
        ),
    )
    p.add_argument("model", type=Path, help=f"model point file ({POINT_FILES})")
    p.add_argument("frames", type=Path, nargs="+", metavar="FRAME", help="frame point files, in order")
    p.add_argument("--out", type=Path, metavar="JSON", help="write the result as JSON")
    add_instance_options(p)
    p.set_defaults(handler=run)
    return p


def load_track():
    """:func:`gatv.motions.track`; RuntimeError if it cannot be imported."""
    from ..io import one_line

    try:
        from ..motions import track
    except ImportError as exc:
        msg = f"the tracking module gatv.motions cannot be imported ({one_line(exc)})."
        raise RuntimeError(msg) from exc
    return track


@guarded
def run(args) -> int:
    """Run ``gatv track`` on parsed ``args``; return the exit status."""
    from ..io import read_points, to_jsonable, write_json

    check_outputs(args, inputs=(args.model, *args.frames))
    options = instance_options(args)
    model = read_points(args.model)
    check_point_counts((("model", model, args.model),), minimum=4)
    frames = [read_points(f) for f in args.frames]
    check_point_counts(((f"frames[{k}]", pts, path) for k, (pts, path) in enumerate(zip(frames, args.frames))))
    track = load_track()
    progress = progress_printer(args)
    start = time.perf_counter()
    with compile_notes(progress, quiet=args.quiet, ahead=True) as notes:
        result = track(model, frames, seed=args.seed, progress=notes.progress, **options)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"frames:          {len(result)}")
        print(f"identities:      {result.n_identities}")
        for f, (found, ids) in enumerate(zip(result.frames, result.identities)):
            missing = result.missing(f)
            gone = f", missing {', '.join(map(str, missing))}" if missing else ""
            print(f"frame {f}:         {len(found)} instances{gone} ({args.frames[f]})")
            for m, ident in zip(found, ids):
                print(f"  identity {ident}:    {describe(m)}")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: no instance of the model found in any frame", file=sys.stderr)
    record = {"model": str(args.model), "frames": [str(f) for f in args.frames], "n_model": len(model),
              "n_frame_points": [len(f) for f in frames], "seed": args.seed, "options": options,
              "success": ok, "time_s": seconds, **result.to_dict(),
              "info": to_jsonable({**result.info, "frames": [f.info for f in result.frames]})}
    write_outputs([(args.out, lambda tmp: write_json(tmp, record))], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
