"""Shared helpers of the benchmark scripts: arguments, timing, tables, CSV.

The scripts run as ``python benchmarks/table1.py`` (this folder is then on
``sys.path``); nothing here is part of the installed package.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "DEFAULT_OUT",
    "add_common_arguments",
    "parse_list",
    "trial_seed",
    "Timer",
    "median",
    "fmt",
    "markdown_table",
    "write_csv",
    "TrialRecord",
    "run_method",
    "summarise",
    "add_scheduler_argument",
    "map_trials",
    "o3d_polish",
]

#: Default output folder: ``benchmarks/results`` beside this file.
DEFAULT_OUT = Path(__file__).resolve().parent / "results"


def add_common_arguments(parser: argparse.ArgumentParser, *, trials: int = 20) -> argparse.ArgumentParser:
    """Add ``--trials``, ``--seed``, ``--out``, ``--fractions``, ``--methods``."""
    parser.add_argument(
        "--trials", type=_positive_int, default=trials, help=f"trials per outlier fraction (default: {trials})"
    )
    parser.add_argument("--seed", type=int, default=0, help="base seed of the trials (default: 0)")
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help=f"folder for the CSV files (default: {DEFAULT_OUT})"
    )
    parser.add_argument(
        "--fractions", type=parse_list(float), default=None, metavar="F,F,...",
        help="outlier fractions to run (default: the paper's)",
    )
    parser.add_argument(
        "--methods", type=parse_list(str), default=None, metavar="M,M,...",
        help="methods to run, comma separated",
    )
    return parser


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def parse_list(kind: Callable) -> Callable[[str], list]:
    """An argparse ``type`` reading a comma-separated list of ``kind``."""

    def parse(text: str) -> list:
        try:
            return [kind(part.strip()) for part in text.split(",") if part.strip()]
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from exc

    return parse


def trial_seed(seed: int, fraction: float, trial: int) -> np.random.SeedSequence:
    """Seed of one trial: independent of the method and of the other rows."""
    return np.random.SeedSequence([int(seed), int(round(1000 * fraction)), int(trial)])


class Timer:
    """Context manager measuring wall-clock seconds in ``.seconds``."""

    def __enter__(self) -> Timer:
        self._start = time.perf_counter()
        self.seconds = float("nan")
        return self

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self._start


def median(values: Iterable[float]) -> float:
    """Median of the finite values; NaN when there is none."""
    arr = np.asarray([v for v in values if v is not None], dtype=float)
    arr = arr[np.isfinite(arr)]
    return float(np.median(arr)) if arr.size else float("nan")


def fmt(value, digits: int = 3) -> str:
    """Format a number for a table; ``—`` for None or NaN."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return f"{value:.{digits}g}" if abs(value) < 1e-3 and value != 0 else f"{value:.{digits}f}"


def markdown_table(headers: Sequence[str], rows: Iterable[Sequence], align: str | None = None) -> str:
    """A GitHub-flavoured markdown table; ``align`` is one of ``lrc`` per column."""
    rows = [[str(c) for c in r] for r in rows]
    widths = [max([len(h)] + [len(r[i]) for r in rows]) for i, h in enumerate(headers)]
    align = align or "l" + "r" * (len(headers) - 1)

    def rule(w, a):
        return {"l": ":" + "-" * (w - 1), "r": "-" * (w - 1) + ":", "c": ":" + "-" * (w - 2) + ":"}[a]

    def line(cells):
        return "| " + " | ".join(
            c.rjust(w) if a == "r" else c.ljust(w) for c, w, a in zip(cells, widths, align)
        ) + " |"

    out = [line(headers), "|" + "|".join(rule(w + 2, a) for w, a in zip(widths, align)) + "|"]
    out += [line(r) for r in rows]
    return "\n".join(out)


def write_csv(path: Path, headers: Sequence[str], rows: Iterable[Sequence]) -> Path:
    """Write a CSV atomically (temporary file, then ``os.replace``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(headers)
            writer.writerows(rows)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass(frozen=True)
class TrialRecord:
    """What one method did on one trial."""

    fraction: float
    method: str
    trial: int
    success: bool
    precision: float
    recall: float
    rotation_error_deg: float
    translation_error: float
    time_s: float
    support: int
    error: str = ""
    extra: dict = field(default_factory=dict)

    HEADERS = (
        "f", "method", "trial", "success", "precision", "recall", "rotation_error_deg",
        "translation_error", "time_s", "support", "error",
    )

    def row(self) -> list:
        return [
            self.fraction, self.method, self.trial, int(self.success), self.precision, self.recall,
            self.rotation_error_deg, self.translation_error, self.time_s, self.support, self.error,
        ]


def run_method(name: str, fn: Callable, trial, fraction: float, index: int) -> TrialRecord:
    """Run ``fn(source, target) -> RigidMotion`` on a trial and score it.

    An exception counts as a failed trial; its message is kept in ``error``.
    """
    from gatv.datasets import correspondence_stats, paper_success, rotation_error_deg, translation_error

    with Timer() as timer:
        try:
            motion = fn(trial.source, trial.target)
            error = ""
        except Exception as exc:  # scored as a failure, reported at the end
            motion, error = None, f"{type(exc).__name__}: {' '.join(str(exc).split())[:160]}"
    if motion is None:
        return TrialRecord(fraction, name, index, False, 0.0, 0.0, float("nan"), float("nan"),
                           timer.seconds, 0, error)
    pairs = motion.correspondences
    precision, recall = correspondence_stats(pairs, trial.true_pairs)
    return TrialRecord(
        fraction, name, index,
        success=bool(paper_success(pairs, trial.true_pairs)),
        precision=precision,
        recall=recall,
        rotation_error_deg=rotation_error_deg(motion.rotation, trial.rotation),
        translation_error=translation_error(motion.translation, trial.translation),
        time_s=timer.seconds,
        support=int(motion.support),
    )


def summarise(records: Sequence[TrialRecord]) -> dict:
    """Success rate (%), medians and error count of one (f, method) cell."""
    return {
        "trials": len(records),
        "success_pct": 100.0 * float(np.mean([r.success for r in records])) if records else float("nan"),
        "precision": median(r.precision for r in records),
        "recall": median(r.recall for r in records),
        "rotation_error_deg": median(r.rotation_error_deg for r in records),
        "time_ms": 1000.0 * median(r.time_s for r in records),
        "errors": sum(bool(r.error) for r in records),
    }


def add_scheduler_argument(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add ``--scheduler``: run the trials as Dask tasks (``local`` or a scheduler address)."""
    parser.add_argument(
        "--scheduler", default=None, metavar="ADDRESS",
        help="run the trials as Dask tasks: 'local' for a LocalCluster on this machine, or a "
             "scheduler address (needs the [distributed] extra); default: serial",
    )
    return parser


def peak_rss_mib() -> float:
    """This process's resident peak (MiB): ``VmHWM`` of ``/proc/self/status`` where there is one.

    ``getrusage(RUSAGE_SELF).ru_maxrss`` of a process started by ``spawn`` (a
    fork and an exec) keeps its parent's peak up to the fork (Linux folds the
    old memory's high-water mark into it at the exec): a child of a parent
    holding 500 MiB reads 529 MiB there against its own 16.  ``VmHWM`` is the
    current memory's own.  Elsewhere ``ru_maxrss`` (KiB on Linux, bytes on
    macOS).
    """
    import resource
    import sys

    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2.0**20 if sys.platform == "darwin" else peak / 1024.0


def map_trials(fn: Callable, tasks: Sequence, *, scheduler: str | None = None) -> list:
    """``[fn(task) for task in tasks]``, serially or as Dask tasks on ``scheduler``.

    ``fn`` and each task must be picklable (a module-level function and plain
    arguments). The results come back in the order of ``tasks`` either way, so a
    table is the same whichever way it was run.
    """
    if scheduler is None:
        return [fn(task) for task in tasks]
    from gatv.batch import map_tasks

    return map_tasks(fn, list(tasks), scheduler=scheduler)


def o3d_polish(source, target, R, t, voxel):
    """Open3D's point-to-plane ICP from ``(R, t)`` within 0.4 voxel: every Open3D or KISS-Matcher peer's polish.

    Returns the polished ``(R, t)``.  Needs the ``[peers]`` extra (Open3D).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = R, t
    T = np.asarray(reg.registration_icp(src, tgt, 0.4 * voxel, start,
                                        reg.TransformationEstimationPointToPlane()).transformation)
    return T[:3, :3], T[:3, 3]
