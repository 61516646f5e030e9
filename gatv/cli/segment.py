"""``gatv segment SOURCE TARGET``: every motion between SOURCE and TARGET (:func:`gatv.motions.segment`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..io import SCALAR_EXTENSIONS
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
from .warmup import compile_notes

__all__ = [
    "LABELLED_EXTENSIONS",
    "NAME",
    "UNEXPLAINED_RGB",
    "add_parser",
    "label_colors",
    "load_segment",
    "render_segmentation",
    "run",
    "write_labelled",
]

#: Files ``--labelled`` writes: PLY (binary, float32 x y z and an int32
#: ``motion`` property per vertex), or VTK PolyData through PyVista; the
#: formats of :data:`gatv.io.SCALAR_EXTENSIONS` that hold a point cloud.
LABELLED_EXTENSIONS = tuple(e for e in SCALAR_EXTENSIONS if e != ".csv")

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
    p.add_argument(
        "--pipeline", choices=("auto", "exact", "scans"), default="auto",
        help="exact: sets whose inliers are the same points in both (noisy or not); scans: dense, "
             "differently sampled range scans (the identity first, motions peeled with the surface "
             "pipeline, each kept only above the chance level); auto: chosen from the data (default)")
    p.add_argument(
        "--time-limit", type=float, metavar="SECONDS",
        help="wall-clock bound on the noisy point-set search (default: 60); past it the motions found "
             "so far are returned, with the reason")
    p.add_argument("--labelled", type=Path, metavar="PLY",
                   help="write the source points with a per-point `motion` scalar (-1: unexplained; "
                        ".ply .vtk .vtp)")
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


#: Colour of points no motion explains in a labelled PLY (light grey).
UNEXPLAINED_RGB = (190, 190, 190)


def label_colors(labels) -> np.ndarray:
    """``(N, 3)`` uint8 colours of motion labels: the picture's palette, grey for -1."""
    from ..render import motion_color, rgb

    labels = np.asarray(labels, dtype=np.int64)
    out = np.empty((labels.shape[0], 3), dtype=np.uint8)
    out[:] = UNEXPLAINED_RGB
    for k in np.unique(labels[labels >= 0]):
        out[labels == k] = rgb(motion_color(int(k)))
    return out


def write_labelled(path, points, labels) -> None:
    """Write ``points`` with an int ``motion`` scalar per point (``labels``) to ``path``.

    :func:`gatv.io.write_points` with ``scalars={"motion": labels}``:

    * ``.ply`` — a binary little-endian PLY with ``float x, y, z``, ``int
      motion`` and ``uchar red, green, blue`` per vertex (the colour of the
      point's motion in ``--render``'s picture, grey for -1).  gatv
      (``read_points(path, scalars=True)["motion"]``), Open3D's tensor API
      (``o3d.t.io.read_point_cloud(path).point["motion"]``), CloudCompare
      and MeshLab read ``motion``.  PyVista's PLY reader (VTK's) reads no
      property beyond coordinates, normals, colours and texture
      coordinates: it shows the colours (``RGB``), and Open3D's legacy
      reader too, but has no ``motion`` array — write ``.vtk`` or ``.vtp``
      for that;
    * ``.vtk``/``.vtp`` — a ``motion`` point array (PyVista, ParaView).
    """
    from ..io import write_points

    labels = np.asarray(labels, dtype=np.int32)
    scalars = {"motion": labels}
    if str(path).lower().endswith(".ply"):
        colors = label_colors(labels)
        scalars.update(red=colors[:, 0], green=colors[:, 1], blue=colors[:, 2])
    write_points(path, np.asarray(points, dtype=np.float64), scalars=scalars)


def _check_labelled(args, inputs) -> None:
    path = args.labelled
    if path is None:
        return
    if path.suffix.lower() not in LABELLED_EXTENSIONS:
        raise UsageError(f"{path}: cannot write labelled points as {path.suffix or 'a file without extension'!r}; "
                         f"expected one of {', '.join(LABELLED_EXTENSIONS)}.")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise UsageError(f"{path}: cannot write labelled points: folder {str(folder)!r} does not exist.")
    others = [Path(x).resolve() for x in (args.out, args.render, *inputs) if x is not None]
    if path.resolve() in others:
        raise UsageError(f"{path}: --labelled must name a file of its own (not an input or another output).")


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
    _check_labelled(args, (args.source, args.target))
    if args.max_motions is not None and args.max_motions < 1:
        raise UsageError(f"expected --max-motions >= 1, got {args.max_motions}.")
    model_options(args)  # a model of 2D points is refused before reading
    source = read_points(args.source)
    target = read_points(args.target)
    check_point_counts((("source", source, args.source), ("target", target, args.target)))
    segment = load_segment()

    options = {k: v for k, v in (("max_motions", args.max_motions), ("min_support", args.min_support),
                                 ("noise", args.noise), ("time_limit", getattr(args, "time_limit", None)))
               if v is not None}
    options.update(model_options(args))
    if getattr(args, "pipeline", "auto") != "auto":
        options["pipeline"] = args.pipeline
    progress = progress_printer(args)
    start = time.perf_counter()
    with compile_notes(progress, quiet=args.quiet, ahead=True) as notes:
        result = segment(source, target, seed=args.seed, progress=notes.progress, **options)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"model:           {args.model}")
        print(f"motions:         {len(result)}")
        for k, m in enumerate(result.motions):
            print(f"motion {k}:        {_describe(m)}, {m.support} correspondences, rms {m.rms:.3g}")
        print(f"unexplained:     {int(np.sum(result.source_labels < 0))} source, "
              f"{int(np.sum(result.target_labels < 0))} target points")
        if "pipeline" in result.info:
            print(f"pipeline:        {result.info['pipeline']} ({result.info.get('pipeline_reason', '')})")
        for d in result.info.get("degenerate", []):
            print(f"degenerate:      a plane-like part of {d['points']} points (a motion could slide along it)")
        for d in result.info.get("ambiguous", []):
            apart = d.get("rival_angle_deg")
            apart = f" ({apart:.0f} deg apart)" if apart is not None else ""
            print(f"ambiguous:       a part of {d['points']} points fits two distinct motions{apart}; "
                  "none reported")
        if result.info.get("reason"):
            print(f"stopped:         {result.info['reason']}")
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
        (getattr(args, "labelled", None), lambda tmp: write_labelled(tmp, source, result.source_labels)),
    ], quiet=args.quiet)
    return EXIT_OK if ok else EXIT_FAILED
