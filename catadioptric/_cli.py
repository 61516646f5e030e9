"""``gatv catadioptric IMAGE1 IMAGE2 --camera CALIB.json``: match the corners of two images.

Detects corners in both images (:func:`catadioptric.detect_corners`),
lifts them to the unit sphere with the camera, matches them
(:func:`catadioptric.match`) and optionally writes the result as JSON and a
Fig. 15-style picture. Wired into :mod:`gatv.cli` by
``add_parser(subparsers)``; ``run(args)`` returns the exit status with the
conventions of ``gatv register``: 0 on success, 1 when nothing was matched,
2 on bad input (one line ``gatv: error: <message>`` on stderr, no
traceback), and no output file unless every output could be written.
"""

from __future__ import annotations

import contextlib
import os
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
from gatv.errors import InputError

__all__ = ["add_parser", "run"]


def add_parser(subparsers):
    """Add the ``catadioptric`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        "catadioptric",
        help="match the corners of two catadioptric images on the unit sphere",
        description=(
            "Detect corners in two catadioptric images, lift them to the unit sphere with a "
            "unified-model camera (JSON: cv2.omnidir K, xi, D or gatv's own layout) and find "
            "one-to-one correspondences (paper section 5.1, Fig. 15). Images: PNG, JPEG, PGM."
        ),
    )
    p.add_argument("image1", type=Path, help="first image")
    p.add_argument("image2", type=Path, help="second image")
    p.add_argument("--camera", type=Path, required=True, metavar="JSON", help="camera calibration")
    p.add_argument("--camera2", type=Path, metavar="JSON", help="camera of IMAGE2 (default: --camera)")
    p.add_argument("--out", type=Path, metavar="JSON", help="write the matches as JSON")
    p.add_argument("--render", type=Path, metavar="PNG", help="write the two images with the matches")
    p.add_argument("--noise-px", type=float, default=1.0, metavar="PX",
                   help="corner noise in pixels (default: 1.0)")
    p.add_argument("--max-corners", type=int, default=400, metavar="N",
                   help="corners detected per image (default: 400)")
    p.add_argument("--strategy", choices=("auto", "rigid", "local", "epipolar", "nonrigid"), default="auto",
                   help="matching strategy (default: auto)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: 0)")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    p.set_defaults(handler=run)
    return p


def _mirror_mask(camera, shape):
    """Pixels the camera can lift (the mirror's disc), as an image mask."""
    import numpy as np

    h, w = shape
    step = 4
    vv, uu = np.mgrid[0:h:step, 0:w:step]
    _, ok = camera.lift(np.column_stack([uu.ravel(), vv.ravel()]).astype(float), return_mask=True)
    coarse = ok.reshape(vv.shape)
    return np.repeat(np.repeat(coarse, step, axis=0), step, axis=1)[:h, :w]


def _run(args) -> int:
    from catadioptric.camera import UnifiedCamera
    from catadioptric.corners import detect_corners, read_image
    from catadioptric.matching import match
    from gatv.io import atomic_path, to_jsonable, write_json

    outs = _check_outputs(args)
    inputs = [args.image1, args.image2, args.camera] + ([args.camera2] if args.camera2 else [])
    for path in inputs:
        if not path.is_file():
            raise InputError(f"{path}: no such file.")
    for out in outs:
        if out in [p.resolve() for p in inputs]:
            raise InputError(f"{out}: refusing to overwrite an input file.")
    if args.max_corners < 3:
        raise InputError(f"Expected --max-corners >= 3, got {args.max_corners}.")
    cam1 = UnifiedCamera.from_file(args.camera)
    cam2 = UnifiedCamera.from_file(args.camera2) if args.camera2 else cam1
    img1, img2 = read_image(args.image1), read_image(args.image2)
    start = time.perf_counter()
    pix1 = detect_corners(img1, max_corners=args.max_corners, mask=_mirror_mask(cam1, img1.shape))
    pix2 = detect_corners(img2, max_corners=args.max_corners, mask=_mirror_mask(cam2, img2.shape))
    t_detect = time.perf_counter() - start
    result = match(pix1, pix2, cam1, cam2, noise_px=args.noise_px, strategy=args.strategy, seed=args.seed)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"corners:         {len(pix1)} / {len(pix2)}")
        print(f"strategy:        {result.strategy}")
        print(f"correspondences: {result.support}")
        if result.rotation is not None:
            print(f"rotation:        {result.rotation_deg:.3f} deg ({result.rotation_support} pairs)")
        if result.translation is not None:
            print(f"translation dir: {' '.join(f'{v:+.4f}' for v in result.translation)}")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: matching failed: {result.info.get('reason', 'nothing matched')}", file=sys.stderr)
    pairs = result.correspondences
    record = {
        "image1": str(args.image1), "image2": str(args.image2), "camera": str(args.camera),
        "camera2": str(args.camera2) if args.camera2 else None,
        "noise_px": args.noise_px, "seed": args.seed, "success": ok,
        "time_s": seconds, "time_detect_s": t_detect,
        "corners1": pix1.tolist(), "corners2": pix2.tolist(),
        **result.to_dict(),
        "matches_px": [[*pix1[i].tolist(), *pix2[j].tolist()] for i, j in pairs],
        "info": to_jsonable(result.info),
    }
    with contextlib.ExitStack() as stack:  # all outputs land together, or none
        if args.out is not None:
            write_json(stack.enter_context(atomic_path(args.out)), record)
        if ok and args.render is not None:
            from catadioptric._render import render_matches

            render_matches(img1, img2, pix1, pix2, pairs, stack.enter_context(atomic_path(args.render)),
                           title=f"{result.support} matches ({result.strategy})")
    if not args.quiet:
        for path in (args.out, args.render if ok else None):
            if path is not None:
                print(f"wrote {path}")
    return EXIT_OK if ok else EXIT_FAILED


def run(args) -> int:
    """Run ``gatv catadioptric`` on parsed ``args``; return the exit status."""
    try:
        return _run(args)
    except (ValueError, OSError) as exc:
        if os.environ.get("GATV_DEBUG"):
            raise
        _error(_one_line(exc))
        return EXIT_USAGE
