"""
Fig. 14: close-up of the joint-space surface, its normals and the local eq.-41 pairs
====================================================================================

For a non-rigid motion eq. 41 holds only locally: each token that tensor
voting kept is checked against its closest active neighbour (paper,
section 5.1 and Fig. 14). This close-up of the surface of Fig. 13 (the same
twisted plane) shows the kept tokens coloured by saliency, their normals
from tensor voting (the local rotation axis used in eq. 41) as arrows, and
each token linked to the neighbour it was verified with; one pair,
``x_i`` and ``x_j``, is picked out as in the paper.

Everything drawn comes from ``NonRigidMotion.diagnostics`` of
:func:`gatv.nonrigid.register`; the truth only gives the printed numbers.
"""

from __future__ import annotations

import argparse
import importlib.util
import time
from pathlib import Path

import numpy as np

from gatv import render
from gatv.nonrigid import register

# sphinx-gallery runs a script in its own folder, without ``__file__`` or ``__doc__``
HERE = Path(globals().get("__file__", "fig14_local_eq41.py")).resolve().parent
#: Radius of the close-up, as a share of the kept tokens' extent.
CLOSE_RADIUS = 0.2
SIZE = (900, 720)


# %%
# The scene of Fig. 13, from its script (same seed, same trial).
def _fig13():
    spec = importlib.util.spec_from_file_location("gallery_fig13_twisted_plane", HERE / "fig13_twisted_plane.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(out_dir, size=SIZE) -> dict:
    """Register the Fig.-13 scene, print the local eq.-41 checks, write ``fig14_local_eq41.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fig13 = _fig13()
    rng = np.random.default_rng(fig13.SEED)
    trial, _, _ = fig13.twisted_plane_trial(rng)
    src, tgt = trial.source, trial.target

    # %%
    # Register; the diagnostics hold the kept tokens, their normals and
    # saliencies, and for each token its verification partner and relaxed
    # eq.-41 residual (over its tolerance; <= 1 passes).
    t0 = time.perf_counter()
    motion = register(src, tgt, seed=0)
    t_reg = time.perf_counter() - t0
    d = motion.diagnostics
    partner = d.verification[:, 1]
    has = partner >= 0
    true = {tuple(r) for r in trial.true_pairs.tolist()}
    is_true = np.array([tuple(r) in true for r in d.pairs.tolist()], bool)
    axis = np.array([1.0, 0.0, 0.0])  # the twist axis: the true local rotation axis everywhere
    tilt = np.degrees(np.arccos(np.clip(np.abs(d.normals @ axis), 0.0, 1.0)))
    print(f"gatv.nonrigid.register ({t_reg:.2f} s): {len(d.tokens)} tokens kept ({int(is_true.sum())} true), "
          f"structure '{d.structure}'")
    print(f"local eq. 41: {int(has.sum())} tokens had an active neighbour, {int(d.verified.sum())} passed; "
          f"residual/tolerance median {np.median(d.residual[has]):.3f}, max {d.residual[has].max():.3f}")
    print(f"token normals vs the twist axis (true tokens): median {np.median(tilt[is_true]):.2f} deg, "
          f"90th percentile {np.percentile(tilt[is_true], 90):.2f} deg")

    # %%
    # The close-up: x_i is the most salient verified token away from the
    # crowded apex of the surface (|d| above the median), with the kept tokens
    # around it; x_j is the neighbour x_i was verified with.
    norm = np.linalg.norm(d.tokens, axis=1)
    ok = np.flatnonzero(d.verified & has & (norm >= np.median(norm)))
    i = int(ok[np.argmax(d.saliency[ok])])
    j = int(partner[i])
    dist = np.linalg.norm(d.tokens - d.tokens[i], axis=1)
    close = np.flatnonzero(dist <= CLOSE_RADIUS * float(np.ptp(d.tokens, axis=0).max()))
    radius = float(dist[close].max())
    links = close[partner[close] >= 0]
    passed = links[d.verified[links]]
    failed = links[~d.verified[links]]
    all_tokens = (tgt[None, :, :] - src[:, None, :]).reshape(-1, 3)
    rejected = np.ones(len(all_tokens), bool)
    rejected[d.pairs[:, 0] * len(tgt) + d.pairs[:, 1]] = False
    near = np.flatnonzero(rejected & (np.linalg.norm(all_tokens - d.tokens[i], axis=1) <= radius))
    near = rng.choice(near, size=min(1500, near.size), replace=False)
    print(f"close-up: {len(close)} kept tokens within {radius:.3f} of x_i (saliency {d.saliency[i]:.1f}); "
          f"{len(passed)} passed / {len(failed)} failed links; x_i-x_j residual/tolerance "
          f"{d.residual[i]:.3f}; {len(near)} rejected tokens nearby drawn")

    # %%
    # The picture: tokens by saliency, normals as arrows, verification links.
    t0 = time.perf_counter()
    pl = render.new_plotter(size)
    saliency_name = "surfaceness" if d.structure == "surface" else "curveness"
    render.add_points(pl, all_tokens[near], color=render.NEUTRAL, size=3, opacity=0.35, label="rejected tokens")
    render.add_correspondences(pl, d.tokens, d.tokens, np.c_[passed, partner[passed]],
                               color=render.PALETTE[2], width=2, label=f"eq. 41 passed ({len(passed)})")
    render.add_correspondences(pl, d.tokens, d.tokens, np.c_[failed, partner[failed]],
                               color=render.PALETTE[3], width=2, label=f"eq. 41 failed ({len(failed)})")
    render.add_correspondences(pl, d.tokens, d.tokens, [[i, j]], color=render.LINE_COLOR, width=5,
                               label="x_i verified with x_j")
    render.add_surface(pl, d.tokens[close], color=render.PALETTE[5], opacity=0.25)
    render.add_normals(pl, d.tokens[close], d.normals[close], scale=0.3 * radius, color=render.LINE_COLOR,
                       label="normal (local axis)")
    render.add_tokens(pl, d.tokens[close], d.saliency[close], title=saliency_name, size=14)
    render.add_points(pl, d.tokens[[i, j]], color=render.LINE_COLOR, size=26, opacity=0.3)
    away = (d.tokens[i] - d.tokens[j]) / max(float(np.linalg.norm(d.tokens[i] - d.tokens[j])), 1e-12)
    for k, name, sign in ((i, "x_i", 1.0), (j, "x_j", -1.0)):  # one call each: labels may not hide each other
        pl.add_point_labels(d.tokens[k] + sign * 0.12 * radius * away, [name],
                            font_size=render.font_size(pl, 16.0), text_color="black", shape_opacity=0.0,
                            show_points=False, always_visible=True, font_family="arial")
    render.add_axes_labels(pl, *fig13.LABELS)
    render.add_title(pl, f"Close-up of the joint-space surface: {len(close)} of {len(d.tokens)} kept tokens")
    render.add_legend(pl, loc="upper left")
    # seen obliquely (the normals in profile, the surface not edge-on)
    c = d.tokens[close] - d.tokens[close].mean(axis=0)
    _, _, (u, _, n) = np.linalg.svd(c, full_matrices=False)
    view = 0.6 * n * np.sign(n @ render.VIEW) + 0.8 * np.cross(n, u) + 0.3 * u
    render.set_view(pl, view / np.linalg.norm(view))
    png = render.save(pl, out_dir / "fig14_local_eq41.png")
    print(f"wrote {Path(png).name} ({size[0]}x{size[1]}, rendered in {time.perf_counter() - t0:.1f} s)")

    return {"pngs": [png], "n_kept": len(d.tokens), "n_verified": int(d.verified.sum()),
            "n_close": len(close), "n_passed": len(passed), "n_failed": len(failed),
            "median_normal_tilt_deg": float(np.median(tilt[is_true]))}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").strip().split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("gallery_out"), help="output folder")
    parser.add_argument("--size", type=int, nargs=2, default=SIZE, metavar=("W", "H"), help="picture size")
    args = parser.parse_args()
    main(args.out, size=tuple(args.size))
