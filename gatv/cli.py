"""Command-line interface: ``gatv register``, ``segment``, ``nonrigid``, ``catadioptric`` and ``demo``.

Installed as the ``gatv`` console script and runnable as ``python -m gatv``.

Exit status: 0 on success, 1 when no motion was found (or on an internal
error), 2 on bad input or options (an unreadable or missing file, wrong
shape, NaN, too few points, any :class:`ValueError` raised by gatv). Errors
are reported as one line ``gatv: error: <message>`` on stderr, never as a
traceback (set ``GATV_DEBUG=1`` to get one), and no output file is written
unless the whole command succeeds: every output is first written to a
temporary file beside its destination and moved into place at the end.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["main", "build_parser"]

PROG = "gatv"
EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class _Usage(ValueError):
    """Bad command-line input detected by the CLI itself."""


class _ArgumentParser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit status 2, no usage dump
        raise _Usage(f"{message} (see `{self.prog} --help`)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``gatv`` command."""
    parser = _ArgumentParser(
        prog=PROG,
        description=(
            "Rigid registration of 3D point sets with Geometric Algebra and Tensor Voting "
            "(Reyes, Medioni & Bayro, IJCV 2007)."
        ),
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_ArgumentParser)

    reg = sub.add_parser(
        "register",
        help="find the rigid motion taking SOURCE onto TARGET",
        description=(
            "Find the rigid motion taking SOURCE onto TARGET (target = R source + t) and their "
            "correspondences, with no initial guess. Point files: .ply .vtk .vtp .stl .obj "
            ".xyz .txt .csv .pts .npy."
        ),
    )
    reg.add_argument("source", type=Path, help="source point file")
    reg.add_argument("target", type=Path, help="target point file")
    reg.add_argument(
        "--scans", action="store_true",
        help="real, differently sampled range scans (gatv.register_scans: surface tokens, "
             "voxel downsampling, normal-pruned trials, point-to-plane polish)",
    )
    _add_run_options(reg)
    reg.set_defaults(handler=_cmd_register)

    demo = sub.add_parser(
        "demo",
        help="register a real mesh shipped with PyVista against a moved, cluttered copy",
        description=(
            "Take the vertices of a small real mesh shipped inside the PyVista wheel (no "
            "download), move a copy by a random rigid motion, add uniform outliers to both, "
            "register, and compare with the known motion."
        ),
    )
    demo.add_argument("--mesh", default="ant", choices=("ant", "airplane", "nut"))
    demo.add_argument(
        "--outliers", type=float, default=0.5, metavar="F",
        help="fraction of outliers added to each set (default: 0.5)",
    )
    demo.add_argument(
        "--motion-seed", type=int, default=1, metavar="N",
        help="seed of the random motion and outliers (default: 1)",
    )
    _add_run_options(demo)
    demo.set_defaults(handler=_cmd_demo)

    seg = sub.add_parser(
        "segment",
        help="find every rigid motion between SOURCE and TARGET (several overlapping motions)",
        description=(
            "Find every rigid motion taking part of SOURCE onto part of TARGET (paper section 5), "
            "each with its own one-to-one correspondences; each point belongs to at most one "
            "motion. The number of motions is found from the data."
        ),
    )
    seg.add_argument("source", type=Path, help="source point file")
    seg.add_argument("target", type=Path, help="target point file")
    seg.add_argument("--out", type=Path, metavar="JSON", help="write the result as JSON")
    seg.add_argument("--render", type=Path, metavar="PNG", help="write an off-screen picture, one colour per motion")
    seg.add_argument("--seed", type=int, default=0, help="seed of the trial search (default: 0)")
    seg.add_argument("--max-motions", type=int, metavar="K", help="return at most K motions (largest first)")
    seg.add_argument("--min-support", type=int, metavar="N",
                     help="correspondences a motion needs (default: from the chance level)")
    seg.add_argument("--noise", type=float, metavar="SIGMA", help="point noise, data units")
    seg.add_argument("--progress", action="store_true", help="print progress lines to stderr")
    seg.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")
    seg.set_defaults(handler=_cmd_segment)

    from .nonrigid._cli import add_parser as add_nonrigid

    add_nonrigid(sub)
    try:
        from catadioptric._cli import add_parser as add_catadioptric
    except ImportError:  # pragma: no cover - the second package is optional at run time
        pass
    else:
        add_catadioptric(sub)
    return parser


def _add_run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, metavar="JSON", help="write the result as JSON")
    p.add_argument(
        "--aligned", type=Path, metavar="FILE",
        help="write the moved source points (.ply .vtk .vtp .xyz .txt .csv .pts .npy)",
    )
    p.add_argument("--render", type=Path, metavar="PNG", help="write an off-screen picture")
    p.add_argument("--seed", type=int, default=0, help="seed of the registration (default: 0)")
    p.add_argument(
        "--max-angle", type=float, metavar="DEG",
        help="bound on the rotation angle in degrees (small-motion mode)",
    )
    p.add_argument(
        "--max-translation", type=float, metavar="DIST",
        help="bound on |t| in data units (with --max-angle)",
    )
    p.add_argument("--noise", type=float, metavar="SIGMA", help="point noise, data units")
    p.add_argument("--progress", action="store_true", help="print progress lines to stderr")
    p.add_argument("--quiet", "-q", action="store_true", help="print nothing on success")


# ------------------------------------------------------------------ helpers
def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


def _error(message: str) -> None:
    print(f"{PROG}: error: {message}", file=sys.stderr, flush=True)


def _check_output(path: Path | None, what: str, extensions: tuple[str, ...] | None) -> None:
    """Fail before any work if an output path cannot be written."""
    if path is None:
        return
    if extensions is not None and path.suffix.lower() not in extensions:
        msg = (
            f"{path}: cannot write {what} as {path.suffix or 'a file without extension'!r}; "
            f"expected one of {', '.join(extensions)}."
        )
        raise _Usage(msg)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise _Usage(f"{path}: cannot write {what}: folder {str(folder)!r} does not exist.")
    if path.is_dir():
        raise _Usage(f"{path}: cannot write {what}: is a folder.")
    if not os.access(folder, os.W_OK):
        raise _Usage(f"{path}: cannot write {what}: folder {str(folder)!r} is not writable.")


def _progress_printer(args):
    if not (args.progress or (not args.quiet and sys.stderr.isatty())):
        return None
    last = [-1.0]

    def progress(fraction, message=""):
        fraction = float(min(max(fraction, 0.0), 1.0))
        if fraction - last[0] < 0.01 and fraction < 1.0 and not message:
            return
        last[0] = fraction
        print(f"{PROG}: [{100 * fraction:5.1f}%] {message}", file=sys.stderr, flush=True)

    return progress


def _options(args) -> dict:
    opts = {}
    if args.max_angle is not None:
        opts["max_angle"] = args.max_angle
    if args.max_translation is not None:
        opts["max_translation"] = args.max_translation
    if args.noise is not None:
        opts["noise"] = args.noise
    return opts


def _load_register(scans: bool = False):
    try:
        if scans:
            from gatv.scans import register_scans as register
        else:
            from gatv.registration import register
    except ImportError as exc:
        msg = f"the registration module gatv.registration cannot be imported ({_one_line(exc)})."
        raise RuntimeError(msg) from exc
    return register


def _axis(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    v = Rotation.from_matrix(rotation).as_rotvec()
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([0.0, 0.0, 1.0])


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in np.asarray(v).ravel()) + "]"


def _summary(motion, seconds: float) -> list[str]:
    lines = []
    if motion:
        lines.append(f"rotation:        {motion.angle_deg:.4f} deg about axis {_fmt(_axis(motion.rotation))}")
        lines.append(f"translation:     {_fmt(motion.translation)}")
    lines.append(f"correspondences: {motion.support}")
    lines.append(f"rms:             {motion.rms:.6g}")
    lines.append(f"time:            {seconds:.3f} s")
    return lines


def _render(source, target, motion, path) -> None:
    from .render import render_registration

    render_registration(source, target, motion, path)


def _run(args, source, target, inputs: dict, extra: dict | None = None) -> tuple[int, object]:
    """Register, print, and write every output atomically; return (status, motion)."""
    from .io import atomic_path, to_jsonable, write_json, write_points

    for name, pts in (("source", source), ("target", target)):
        if len(pts) < 3:
            raise _Usage(f"{inputs[name]}: expected at least 3 points in `{name}`, got {len(pts)}.")
    scans = bool(getattr(args, "scans", False))
    register = _load_register(scans)
    options = _options(args)
    if scans and options:
        raise _Usage(f"--scans takes no {', '.join('--' + k.replace('_', '-') for k in options)}.")
    progress = _progress_printer(args)
    call = dict(options)
    if progress is not None:
        call["progress"] = progress
    start = time.perf_counter()
    motion = register(source, target, seed=args.seed, **call)
    seconds = time.perf_counter() - start

    ok = bool(motion)
    if not args.quiet:
        for line in _summary(motion, seconds):
            print(line)
    if not ok:
        reason = motion.info.get("reason", "no motion found") if hasattr(motion, "info") else "no motion found"
        print(f"{PROG}: registration failed: {reason}", file=sys.stderr)

    record = {
        **inputs,
        "n_source": int(len(source)),
        "n_target": int(len(target)),
        "seed": args.seed,
        "options": options,
        "success": ok,
        "time_s": seconds,
        **motion.to_dict(),
        "info": to_jsonable(getattr(motion, "info", {})),
    }
    if extra:
        record.update(extra)
    with contextlib.ExitStack() as stack:  # all outputs land together, or none
        if args.out is not None:
            write_json(stack.enter_context(atomic_path(args.out)), record)
        if ok and args.aligned is not None:
            write_points(stack.enter_context(atomic_path(args.aligned)), motion.transform(source))
        if ok and args.render is not None:
            _render(source, target, motion, stack.enter_context(atomic_path(args.render)))
    if not args.quiet:
        for path in (args.out, args.aligned if ok else None, args.render if ok else None):
            if path is not None:
                print(f"wrote {path}")
    return (EXIT_OK if ok else EXIT_FAILED), motion


def _check_outputs(args) -> list[Path]:
    """Fail before any work if an output (--out, --aligned, --render) cannot be written.

    Serves every subcommand: only the output options its parser has are
    checked.  Returns the resolved paths of the outputs asked for.
    """
    from .io import WRITE_EXTENSIONS

    kinds = (("out", "the result", None), ("aligned", "aligned points", WRITE_EXTENSIONS),
             ("render", "a picture", _IMAGE_EXTENSIONS))
    present = [(dest, what, ext) for dest, what, ext in kinds if hasattr(args, dest)]
    for dest, what, ext in present:
        _check_output(getattr(args, dest), what, ext)
    outs = [getattr(args, dest).resolve() for dest, _, _ in present if getattr(args, dest) is not None]
    if len(set(outs)) != len(outs):
        flags = [f"--{dest}" for dest, _, _ in present]
        names = ", ".join(flags[:-1]) + " and " + flags[-1]
        raise _Usage(f"{names} must name different files.")
    return outs


# ----------------------------------------------------------------- commands
def _cmd_register(args) -> int:
    from .io import read_points

    _check_outputs(args)
    source = read_points(args.source)
    target = read_points(args.target)
    for out in (args.out, args.aligned, args.render):
        if out is not None and out.resolve() in (args.source.resolve(), args.target.resolve()):
            raise _Usage(f"{out}: refusing to overwrite an input file.")
    inputs = {"source": str(args.source), "target": str(args.target)}
    return _run(args, source, target, inputs)[0]


def _cmd_demo(args) -> int:
    from .datasets import (
        correspondence_stats,
        demo_mesh,
        rotation_error_deg,
        synthetic_trial,
        translation_error,
    )

    _check_outputs(args)
    if not (0.0 <= args.outliers < 1.0):
        raise _Usage(f"expected --outliers in [0, 1), got {args.outliers!r}.")
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
    source, target, R, t = trial.source, trial.target, trial.rotation, trial.translation
    status, motion = _run(args, source, target, inputs, extra=extra)
    precision, recall = correspondence_stats(motion.correspondences, trial.true_pairs)
    if not args.quiet:
        print(
            f"vs truth:        rotation error {rotation_error_deg(motion.rotation, R):.4g} deg, "
            f"translation error {translation_error(motion.translation, t):.4g}, "
            f"precision {precision:.3f}, recall {recall:.3f}"
        )
    return status


def _render_segmentation(source, target, segmentation, path) -> None:
    from .render import render_segmentation

    render_segmentation(source, target, segmentation, path)


def _cmd_segment(args) -> int:
    from .io import atomic_path, read_points, to_jsonable, write_json

    _check_outputs(args)
    if args.max_motions is not None and args.max_motions < 1:
        raise _Usage(f"expected --max-motions >= 1, got {args.max_motions}.")
    source = read_points(args.source)
    target = read_points(args.target)
    for out in (args.out, args.render):
        if out is not None and out.resolve() in (args.source.resolve(), args.target.resolve()):
            raise _Usage(f"{out}: refusing to overwrite an input file.")
    for name, pts, path in (("source", source, args.source), ("target", target, args.target)):
        if len(pts) < 3:
            raise _Usage(f"{path}: expected at least 3 points in `{name}`, got {len(pts)}.")
    from .motions import segment

    options = {k: v for k, v in (("max_motions", args.max_motions), ("min_support", args.min_support),
                                 ("noise", args.noise)) if v is not None}
    progress = _progress_printer(args)
    start = time.perf_counter()
    result = segment(source, target, seed=args.seed, progress=progress, **options)
    seconds = time.perf_counter() - start
    ok = bool(result)
    if not args.quiet:
        print(f"motions:         {len(result)}")
        for k, m in enumerate(result.motions):
            print(f"motion {k}:        {m.angle_deg:.4f} deg about axis {_fmt(_axis(m.rotation))}, "
                  f"t = {_fmt(m.translation)}, {m.support} correspondences, rms {m.rms:.3g}")
        print(f"unexplained:     {int(np.sum(result.source_labels < 0))} source, "
              f"{int(np.sum(result.target_labels < 0))} target points")
        print(f"time:            {seconds:.3f} s")
    if not ok:
        print(f"{PROG}: segmentation found no motion: "
              f"{result.info.get('reason', 'no plane with enough support')}", file=sys.stderr)
    record = {"source": str(args.source), "target": str(args.target), "n_source": int(len(source)),
              "n_target": int(len(target)), "seed": args.seed, "options": options, "success": ok,
              "time_s": seconds, **result.to_dict(), "info": to_jsonable(result.info)}
    with contextlib.ExitStack() as stack:  # all outputs land together, or none
        if args.out is not None:
            write_json(stack.enter_context(atomic_path(args.out)), record)
        if ok and args.render is not None:
            _render_segmentation(source, target, result, stack.enter_context(atomic_path(args.render)))
    if not args.quiet:
        for path in (args.out, args.render if ok else None):
            if path is not None:
                print(f"wrote {path}")
    return EXIT_OK if ok else EXIT_FAILED


# --------------------------------------------------------------------- main
def main(argv=None) -> int:
    """Run the ``gatv`` command; return its exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 success, 1 no motion found or internal error, 2 bad input.
    """
    parser = build_parser()
    debug = bool(os.environ.get("GATV_DEBUG"))
    try:
        args = parser.parse_args(argv)
        if args.version:
            from importlib.metadata import PackageNotFoundError, version

            try:
                print(f"{PROG} {version('gatv')}")
            except PackageNotFoundError:
                print(f"{PROG} (version unknown)")
            return EXIT_OK
        if args.command is None:
            parser.print_help()
            return EXIT_USAGE
        return int(args.handler(args))
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    except KeyboardInterrupt:
        _error("interrupted")
        return 130
    except (ValueError, OSError) as exc:  # PointFileError, gatv validators, writes
        if debug:
            raise
        _error(_one_line(exc))
        return EXIT_USAGE
    except Exception as exc:
        if debug:
            raise
        _error(f"{type(exc).__name__}: {_one_line(exc)} (set GATV_DEBUG=1 for a traceback)")
        return EXIT_FAILED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
