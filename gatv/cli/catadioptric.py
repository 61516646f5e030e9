"""``gatv catadioptric IMAGE1 IMAGE2 --camera CALIB.json``: match the corners of two images.

Detects corners in both images (:func:`catadioptric.detect_corners`), lifts
them to the unit sphere with the camera, matches them
(:func:`catadioptric.match`: every motion, the dominant one first) and
optionally writes the result as JSON and a Fig. 15-style picture. The JSON
has a list ``motions``, each with its ``correspondences``, ``matches_px``,
rotation and translation direction; the top-level ``matches_px`` holds the
matches of all motions.  The :mod:`catadioptric` package (the second
top-level package of the distribution) is imported only when the command
runs; when it cannot be imported the command fails with exit status 1 and
the rest of ``gatv`` is unaffected.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ._common import (
    EXIT_FAILED,
    EXIT_OK,
    PROG,
    UsageError,
    add_outputs,
    add_verbosity,
    check_outputs,
    guarded,
    write_outputs,
)

__all__ = ["NAME", "add_parser", "run"]

NAME = "catadioptric"


def add_parser(subparsers):
    """Add the ``catadioptric`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
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
    add_outputs(p, out="write the matches as JSON", render="write the two images with the matches")
    p.add_argument("--noise-px", type=float, default=1.0, metavar="PX",
                   help="corner noise in pixels (default: 1.0)")
    p.add_argument("--max-corners", type=int, default=400, metavar="N",
                   help="corners detected per image (default: 400)")
    p.add_argument("--strategy", choices=("auto", "rigid", "local", "epipolar", "nonrigid", "voting"),
                   default="auto", help="matching strategy of the dominant motion (default: auto)")
    p.add_argument("--max-motions", type=int, default=3, metavar="N",
                   help="most motions reported: after the dominant one, planes moved rigidly are "
                        "looked for on the corners left (default: 3; 1: the dominant motion only)")
    p.add_argument("--seed", type=int, default=0, help="seed (default: 0)")
    add_verbosity(p, progress=False)
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


def _import_catadioptric():
    """The :mod:`catadioptric` package, imported now; RuntimeError if it cannot be."""
    from ..io import one_line

    try:
        import catadioptric
    except ImportError as exc:
        raise RuntimeError(f"the catadioptric package cannot be imported ({one_line(exc)}).") from exc
    return catadioptric


def _render(image1, image2, pixels1, pixels2, motions, path, title) -> None:
    import numpy as np

    from catadioptric.render import render_matches

    pairs = np.vstack([m.correspondences for m in motions]) if motions else np.empty((0, 2), np.int64)
    which = np.concatenate([np.full(m.support, k) for k, m in enumerate(motions)]) if motions else None
    render_matches(image1, image2, pixels1, pixels2, pairs, path, title=title, motion=which)


@guarded
def run(args) -> int:
    """Run ``gatv catadioptric`` on parsed ``args``; return the exit status."""
    from ..io import to_jsonable, write_json

    inputs = [args.image1, args.image2, args.camera] + ([args.camera2] if args.camera2 else [])
    check_outputs(args, inputs=inputs)
    for path in inputs:
        if not path.is_file():
            raise UsageError(f"{path}: no such file.")
    if args.max_corners < 3:
        raise UsageError(f"Expected --max-corners >= 3, got {args.max_corners}.")
    if args.max_motions < 1:
        raise UsageError(f"Expected --max-motions >= 1, got {args.max_motions}.")
    cata = _import_catadioptric()
    cam1 = cata.UnifiedCamera.from_file(args.camera)
    cam2 = cata.UnifiedCamera.from_file(args.camera2) if args.camera2 else cam1
    img1, img2 = cata.read_image(args.image1), cata.read_image(args.image2)
    start = time.perf_counter()
    pix1 = cata.detect_corners(img1, max_corners=args.max_corners, mask=_mirror_mask(cam1, img1.shape))
    pix2 = cata.detect_corners(img2, max_corners=args.max_corners, mask=_mirror_mask(cam2, img2.shape))
    t_detect = time.perf_counter() - start
    result = cata.match(pix1, pix2, cam1, cam2, noise_px=args.noise_px, strategy=args.strategy, seed=args.seed,
                        max_motions=args.max_motions)
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
        print(f"motions:         {len(result.motions)}")
        for k, motion in enumerate(result.motions, start=1):
            rot = "" if motion.angle_deg is None else f", rotation {motion.angle_deg:.3f} deg"
            print(f"  motion {k}:      {motion.support} pairs ({motion.strategy}{rot})")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: matching failed: {result.info.get('reason', 'nothing matched')}", file=sys.stderr)
    pairs = result.correspondences

    def matches_px(c):
        return [[*pix1[i].tolist(), *pix2[j].tolist()] for i, j in c]

    motions = [{**m.to_dict(), "matches_px": matches_px(m.correspondences), "info": to_jsonable(m.info)}
               for m in result.motions]
    record = {
        "image1": str(args.image1), "image2": str(args.image2), "camera": str(args.camera),
        "camera2": str(args.camera2) if args.camera2 else None,
        "noise_px": args.noise_px, "seed": args.seed, "success": ok,
        "time_s": seconds, "time_detect_s": t_detect,
        "corners1": pix1.tolist(), "corners2": pix2.tolist(),
        **result.to_dict(),
        "motions": motions,
        "matches_px": matches_px(pairs),
        "info": to_jsonable(result.info),
    }
    title = f"{result.support} matches, {len(result.motions)} motion{'s' * (len(result.motions) != 1)} " + (
        f"({', '.join(f'{m.support} {m.strategy}' for m in result.motions)})")
    write_outputs([
        (args.out, lambda tmp: write_json(tmp, record)),
        (args.render if ok else None,
         lambda tmp: _render(img1, img2, pix1, pix2, result.motions, tmp, title)),
    ], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
