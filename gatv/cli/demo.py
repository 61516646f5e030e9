"""``gatv demo``: register a real mesh shipped with PyVista against a moved, cluttered copy."""

from __future__ import annotations

import numpy as np

from ._common import UsageError, check_outputs, guarded
from .register import add_run_options, register_and_write

__all__ = ["NAME", "add_parser", "run"]

NAME = "demo"


def add_parser(subparsers):
    """Add the ``demo`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="register a real mesh shipped with PyVista against a moved, cluttered copy",
        description=(
            "Take the vertices of a small real mesh shipped inside the PyVista wheel (no "
            "download), move a copy by a random rigid motion, add uniform outliers to both, "
            "register, and compare with the known motion."
        ),
    )
    p.add_argument("--mesh", default="ant", choices=("ant", "airplane", "nut"))
    p.add_argument(
        "--outliers", type=float, default=0.5, metavar="F",
        help="fraction of outliers added to each set (default: 0.5)",
    )
    p.add_argument(
        "--motion-seed", type=int, default=1, metavar="N",
        help="seed of the random motion and outliers (default: 1)",
    )
    add_run_options(p)
    p.set_defaults(handler=run)
    return p


@guarded
def run(args) -> int:
    """Run ``gatv demo`` on parsed ``args``; return the exit status."""
    from ..datasets import (
        correspondence_stats,
        demo_mesh,
        rotation_error_deg,
        synthetic_trial,
        translation_error,
    )

    check_outputs(args)
    if not (0.0 <= args.outliers < 1.0):
        raise UsageError(f"expected --outliers in [0, 1), got {args.outliers!r}.")
    mesh = demo_mesh(args.mesh)
    # the paper's Table 2 protocol with the mesh's vertices as inliers, and
    # translations up to the mesh's size
    size = float(np.ptp(mesh, axis=0).max())
    trial = synthetic_trial(args.outliers, inliers=mesh, max_translation=size, seed=args.motion_seed)
    if not args.quiet:
        print(
            f"demo: {args.mesh} mesh, {len(mesh)} vertices + {trial.n_outliers} outliers in each set; "
            f"true motion {trial.angle_deg:.2f} deg, |t| = {np.linalg.norm(trial.translation):.4g}"
        )
    inputs = {"source": f"demo:{args.mesh}", "target": f"demo:{args.mesh} (moved)"}
    extra = {"true_rotation": trial.rotation, "true_translation": trial.translation}
    status, motion = register_and_write(args, trial.source, trial.target, inputs, extra=extra)
    precision, recall = correspondence_stats(motion.correspondences, trial.true_pairs)
    if not args.quiet:
        print(
            f"vs truth:        rotation error {rotation_error_deg(motion.rotation, trial.rotation):.4g} deg, "
            f"translation error {translation_error(motion.translation, trial.translation):.4g}, "
            f"precision {precision:.3f}, recall {recall:.3f}"
        )
    return status
