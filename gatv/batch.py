"""Batches of independent registrations, serially or as Dask tasks.

A registration study is thousands of independent pairs.  :func:`run` takes a
table of pairs (a CSV file with the columns ``source`` and ``target``, or a
list of mappings), runs one command (``register``, ``segment``,
``instances`` or ``nonrigid``) on each row and writes one JSON per row, with the schema of
``gatv register --out`` (the same record: ``source``, ``target``, sizes,
``seed``, ``options``, ``success``, ``time_s``, the result's ``to_dict()``
including its 4×4 ``matrix``, ``info``), plus a ``batch`` block naming the
row, and ``summary.csv`` with one line per row.

Where the work runs (``scheduler``):

* ``"auto"`` (default) — rows run in this process while their cost is
  measured; a local cluster (as ``"local"``) is started for the rows left
  only when it is expected to finish them sooner, its start included
  (:func:`local_cluster_pays`: a batch of short rows stays serial, as a
  cluster's start costs more than it saves); ``BatchResult.where`` says
  which was chosen and why;
* ``"local"`` — a :class:`dask.distributed.LocalCluster` on this
  machine: ``workers`` processes (default: one per core) with one thread
  each, numba limited to the cores a worker owns;
* an address such as ``"tcp://10.0.0.5:8786"`` — an existing Dask
  scheduler; its workers must have gatv installed and see the input paths;
  each worker thread runs numba on its host's cores over the worker
  threads of that host (:func:`numba_plan`: one thread for two
  single-threaded workers on two cores);
* a :class:`dask.distributed.Client` — used as it is and not closed;
* ``"serial"`` — in this process, one row after the other (no Dask).

On Dask, rows that take less than about :data:`TASK_SECONDS` are grouped
into one task (``chunk``), so that Dask's own cost per task stays small.

Guarantees:

* A row's result does not depend on where it ran: the task is the same pure
  function of its row (seed included) — results equal the serial ones bit
  for bit, apart from ``time_s``.
* A failing row (missing or unreadable file, NaN, too few points, a bad
  option value, a worker lost more than Dask's ``allowed-failures`` times)
  records its error in its JSON (``"error"``, ``"error_type"``) and the
  batch goes on.  A worker killed while running a task is replaced and the
  task re-run by Dask; ``retries`` re-runs a task that raised.
* Resumable: a row whose JSON exists, holds a completed result (found or
  not) and was made from the same row (command, paths, seed, options) is
  not run again.  Rows that failed are run again.
* Every file is written atomically (a temporary file moved into place): an
  interrupted batch leaves finished JSONs and no partial one.  Nothing is
  written before the table, the command and the scheduler were checked.

:func:`map_tasks` is the generic seam (``[fn(t) for t in tasks]`` on Dask,
in task order) that the benchmark scripts use for ``--scheduler``.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import csv
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._validation import check_int, check_progress
from .errors import InputError
from .io import one_line, result_record, to_jsonable, write_json, write_matrix
from .models import MODEL_NAMES

__all__ = [
    "COMMANDS",
    "LOCAL_CLUSTER_CONFIG",
    "LOCAL_START_SECONDS",
    "MEASURED_ROWS",
    "ROW_OPTIONS",
    "SUMMARY_HEADERS",
    "TASK_SECONDS",
    "BatchResult",
    "RowResult",
    "StartDecision",
    "Task",
    "compute",
    "connect",
    "local_cluster_pays",
    "map_tasks",
    "numba_plan",
    "read_pairs",
    "run",
]

#: Commands a batch can run.
#: ``instances`` reads ``source`` as the model and ``target`` as the scene.
COMMANDS = ("register", "segment", "instances", "nonrigid")

#: Values of the ``model`` column: the registry's models (a model of 2D points
#: fails its rows with the model's own message).
_MODELS = MODEL_NAMES
_PREALIGN = {"auto": "auto", "always": True, "never": False, "true": True, "false": False}


def _bool(text) -> bool:
    if isinstance(text, bool):
        return text
    value = str(text).strip().lower()
    if value in ("1", "true", "yes", "y"):
        return True
    if value in ("0", "false", "no", "n"):
        return False
    raise ValueError(f"expected true or false, got {text!r}")


def _int(text) -> int:
    if isinstance(text, (int, np.integer)) and not isinstance(text, bool):
        return int(text)
    try:
        value = float(str(text).strip())
    except ValueError:
        raise ValueError(f"expected an integer, got {text!r}") from None
    if not math.isfinite(value) or not value.is_integer():
        raise ValueError(f"expected an integer, got {text!r}")
    return int(value)


def _float(text) -> float:
    try:
        value = float(str(text).strip()) if not isinstance(text, (int, float)) else float(text)
    except ValueError:
        raise ValueError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"expected a finite number, got {text!r}")
    return value


def _choice(choices) -> Callable:
    def parse(text):
        value = str(text).strip().lower()
        if value not in choices:
            raise ValueError(f"expected one of {', '.join(choices)}, got {text!r}")
        return value

    return parse


#: Per-row options of each command (CSV columns besides ``source``, ``target``
#: and ``name``): column -> parser.  Empty cells take the batch's default.
ROW_OPTIONS: dict[str, dict[str, Callable]] = {
    "register": {"seed": _int, "model": _choice(_MODELS), "max_angle": _float,
                 "max_translation": _float, "noise": _float, "scans": _bool},
    "segment": {"seed": _int, "model": _choice(_MODELS), "max_motions": _int, "min_support": _int,
                "noise": _float},
    "instances": {"seed": _int, "max_instances": _int, "pipeline": _choice(("auto", "exact", "scans")),
                  "time_limit": _float},
    "nonrigid": {"seed": _int, "max_displacement": _float, "noise": _float,
                 "prealign": _choice(tuple(_PREALIGN))},
}

#: Columns of ``summary.csv``.  The ``verdict_*`` columns hold the result's
#: ``info["verdict"]`` (its support, the chance level it had to beat and its
#: p-value; :mod:`gatv.verdict`) and are empty for a result without one.
SUMMARY_HEADERS = ("row", "name", "status", "success", "support", "rms", "time_s", "source", "target",
                   "seed", "reused", "error", "json", "verdict_support", "verdict_chance", "verdict_p")


# ------------------------------------------------------------------ the rows
@dataclass(frozen=True)
class Task:
    """One row of a batch: what :func:`compute` needs, picklable and hashable.

    Attributes
    ----------
    row : int
        0-based index of the row in the table (the header is not a row).
    name : str
        Stem of the row's JSON (``name`` column, else ``row-00012``).
    command : str
        ``register``, ``segment`` or ``nonrigid``.
    source, target : str
        Absolute paths of the point files.
    seed : int
    options : tuple of (str, value)
        The command's keyword options, sorted by name.
    problem : str
        Why the row cannot run (a bad cell); empty when it can.
    """

    row: int
    name: str
    command: str
    source: str
    target: str
    seed: int = 0
    options: tuple = ()
    problem: str = ""

    def key(self) -> dict:
        """What a finished JSON must have been made from for the row to be skipped."""
        return to_jsonable({"command": self.command, "source": self.source, "target": self.target,
                            "seed": self.seed, "options": dict(self.options)})


def _normalise(column: str) -> str:
    return column.strip().lower().replace("-", "_").replace(" ", "_")


def _check_command(command) -> str:
    if command not in COMMANDS:
        msg = f"Expected `command` to be one of {', '.join(COMMANDS)}, got {command!r}."
        raise InputError(msg)
    return command


def read_pairs(pairs, *, command: str = "register", seed: int = 0, defaults: Mapping | None = None,
               base=None) -> list[Task]:
    """The tasks of a table of pairs.

    Parameters
    ----------
    pairs : str, path-like or sequence of mappings
        A CSV file whose header names the columns, or rows as dictionaries.
        Columns: ``source`` and ``target`` (point files; relative paths are
        relative to the CSV's folder, or to ``base``), optionally ``name``
        (the stem of the row's JSON; default ``row-00012``) and the
        command's options of :data:`ROW_OPTIONS` (``seed``, ``model``,
        ``noise``...; dashes and underscores alike).
    command : {"register", "segment", "instances", "nonrigid"}, default: "register"
    seed : int, default: 0
        Seed of the rows without a ``seed`` cell.
    defaults : mapping, optional
        Option values for empty or missing cells (as strings or values).
    base : path-like, optional
        Folder of relative paths; default the CSV's folder, or the working
        folder for rows given as mappings.

    Returns
    -------
    list of Task
        In table order.  A row with a bad cell gets a task whose
        ``problem`` says why (it is recorded as failed, the others run).

    Raises
    ------
    InputError
        A missing or unreadable CSV, no ``source`` or ``target`` column, an
        unknown column, no row, a repeated name, or a bad default.
    """
    command = _check_command(command)
    seed = check_int(seed, "seed", 0)
    parsers = ROW_OPTIONS[command]
    rows, columns, where = _rows(pairs)
    folder = Path(base) if base is not None else (
        Path(pairs).resolve().parent if isinstance(pairs, (str, os.PathLike)) else Path.cwd())
    missing = [c for c in ("source", "target") if c not in columns]
    if missing:
        msg = (f"{where}: expected the columns `source` and `target`, missing "
               f"{' and '.join(f'`{c}`' for c in missing)} (got {', '.join(columns) or 'no header'}).")
        raise InputError(msg)
    unknown = [c for c in columns if c not in ("source", "target", "name", *parsers)]
    if unknown:
        msg = (f"{where}: unknown column{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} for "
               f"`{command}`; expected source, target, name, {', '.join(parsers)}.")
        raise InputError(msg)
    if not rows:
        raise InputError(f"{where}: no rows; expected one pair per line after the header.")
    fallback = {}
    for key, value in (defaults or {}).items():
        key = _normalise(key)
        if key not in parsers:
            raise InputError(f"unknown option {key!r} for `{command}`; expected one of {', '.join(parsers)}.")
        try:
            fallback[key] = parsers[key](value)
        except ValueError as exc:
            raise InputError(f"bad value for option {key!r}: {exc}.") from None
    fallback.setdefault("seed", seed)

    tasks, names = [], {}
    for index, row in enumerate(rows):
        name = str(row.get("name") or "").strip() or f"row-{index:05d}"
        if not _safe_name(name):
            msg = f"{where}: row {index}: name {name!r} is not a plain file name (letters, digits, ._-)."
            raise InputError(msg)
        if name in names:
            raise InputError(f"{where}: rows {names[name]} and {index} have the same name {name!r}.")
        names[name] = index
        paths, values, problems = {}, dict(fallback), []
        for col in ("source", "target"):
            text = str(row.get(col) or "").strip()
            if not text:
                problems.append(f"empty `{col}`")
            paths[col] = str((folder / text).resolve()) if text else ""
        for col, parse in parsers.items():
            cell = row.get(col)
            if cell is None or (isinstance(cell, str) and not cell.strip()):
                continue
            try:
                values[col] = parse(cell)
            except ValueError as exc:
                problems.append(f"`{col}`: {exc}")
        if values["seed"] < 0:
            problems.append(f"`seed`: expected a non-negative integer, got {values['seed']}")
        row_seed = int(values.pop("seed"))
        tasks.append(Task(row=index, name=name, command=command, source=paths["source"],
                          target=paths["target"], seed=row_seed, options=tuple(sorted(values.items())),
                          problem="; ".join(problems)))
    return tasks


def _safe_name(name: str) -> bool:
    return all(ch.isalnum() or ch in "._-" for ch in name) and not name.startswith(".")


def _rows(pairs) -> tuple[list[dict], list[str], str]:
    if isinstance(pairs, (str, os.PathLike)):
        path = Path(pairs)
        if not path.is_file():
            raise InputError(f"{path}: no such CSV file." if not path.exists() else f"{path}: not a file.")
        try:
            with open(path, newline="", encoding="utf-8-sig") as fh:
                reader = csv.DictReader(fh)
                columns = [_normalise(c) for c in (reader.fieldnames or []) if c is not None]
                rows = [{_normalise(k): v for k, v in r.items() if k is not None} for r in reader
                        if any((v or "").strip() for v in r.values() if isinstance(v, str))]
        except (UnicodeDecodeError, csv.Error) as exc:
            raise InputError(f"{path}: cannot be read as CSV ({one_line(exc)}).") from exc
        return rows, columns, str(path)
    if isinstance(pairs, Mapping) or not isinstance(pairs, Iterable):
        msg = f"Expected `pairs` to be a CSV path or a sequence of mappings, got {type(pairs).__name__}."
        raise InputError(msg)
    rows = []
    for k, r in enumerate(pairs):
        if not isinstance(r, Mapping):
            raise InputError(f"Expected `pairs[{k}]` to be a mapping with source and target, got {r!r}.")
        rows.append({_normalise(str(c)): v for c, v in r.items()})
    columns = list(dict.fromkeys(c for r in rows for c in r))
    return rows, columns, "pairs"


# ---------------------------------------------------------------- one task
def _call(task: Task):
    """Read the task's files and run its command; return ``(source, target, options, result, seconds)``.

    ``seconds`` times the command alone, as ``gatv register`` does.
    """
    from .io import read_points

    source = read_points(task.source)
    target = read_points(task.target)
    for what, pts, path in (("source", source, task.source), ("target", target, task.target)):
        if len(pts) < 3:
            raise InputError(f"{path}: expected at least 3 points in `{what}`, got {len(pts)}.")
    opts = dict(task.options)
    if task.command == "register" and opts.pop("scans", False):
        if opts:
            raise InputError(f"`scans` takes no {', '.join(sorted(opts))}.")
        from .scans import register_scans as fn
    elif task.command == "register":
        from .registration import register as fn
    elif task.command == "segment":
        from .motions import segment as fn
    elif task.command == "instances":
        from .motions import instances as fn
    else:
        from .nonrigid import register as fn

        if "prealign" in opts:
            opts["prealign"] = _PREALIGN[opts["prealign"]]
    if opts.get("model") == "rigid":
        opts.pop("model")
    start = time.perf_counter()
    result = fn(source, target, seed=task.seed, **opts)
    return source, target, opts, result, time.perf_counter() - start


def compute(task: Task) -> dict:
    """The JSON record of one row; never raises.

    Runs the task's command on its files exactly as the command line does
    (same function, same seed), and returns :func:`gatv.io.result_record`'s
    record plus ``"batch"``.  An exception becomes ``"success": false``
    with ``"error"`` (one line) and ``"error_type"``.
    """
    inputs = {"source": task.source, "target": task.target}
    batch = {"row": task.row, "name": task.name, "task": task.key()}
    start = time.perf_counter()
    try:
        if task.problem:
            raise InputError(f"row {task.row}: {task.problem}.")
        source, target, options, result, seconds = _call(task)
    except Exception as exc:  # noqa: BLE001 - any failure is recorded in the row's JSON; the batch goes on
        return {**inputs, "seed": task.seed, "options": to_jsonable(dict(task.options)),
                "success": False, "time_s": time.perf_counter() - start,
                "error": one_line(exc, limit=None), "error_type": type(exc).__name__, "batch": batch}
    record = result_record(inputs, source, target, seed=task.seed, options=options, seconds=seconds,
                           result=result)
    record["batch"] = batch
    return record


def _compute_rows(tasks: tuple, plan: Mapping | None = None) -> tuple[list[dict], float]:
    """:func:`compute` on several rows in one Dask task: their records and the seconds taken.

    ``plan`` maps worker addresses to numba threads (:func:`numba_plan`);
    the worker thread running the task is pinned to its entry (1 for a
    worker the plan does not know).
    """
    if plan is not None:
        _pin_numba(plan)
    start = time.perf_counter()
    return [compute(t) for t in tasks], time.perf_counter() - start


def _pin_numba(plan: Mapping) -> int | None:
    """Limit numba's threads, for the calling thread, to this worker's entry of ``plan``."""
    try:
        from distributed import get_worker

        address = get_worker().address
    except (ImportError, ValueError):  # not on a Dask worker
        return None
    import numba

    n = max(1, min(int(plan.get(address, 1)), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def _lost(task: Task, exc: BaseException) -> dict:
    """The record of a task Dask gave up on (worker lost too often, cancelled)."""
    return {"source": task.source, "target": task.target, "seed": task.seed,
            "options": to_jsonable(dict(task.options)), "success": False, "time_s": None,
            "error": f"the task did not complete: {one_line(exc, limit=None)}",
            "error_type": type(exc).__name__,
            "batch": {"row": task.row, "name": task.name, "task": task.key()}}


# ------------------------------------------------------------------ results
@dataclass(frozen=True)
class RowResult:
    """What happened to one row.

    ``status`` is ``"found"`` (a motion), ``"not found"`` (the command ran
    and found nothing: a result, not a failure) or ``"failed"`` (an error,
    in ``error``).  ``reused`` is True when an earlier run's JSON was kept.
    """

    row: int
    name: str
    status: str
    path: Path
    reused: bool = False
    error: str = ""
    record: dict = field(default_factory=dict, repr=False, compare=False)

    def __bool__(self) -> bool:
        return self.status != "failed"


@dataclass(frozen=True)
class BatchResult:
    """The rows of a batch, in table order, and where they were written.

    ``where`` says where the rows ran and, for ``scheduler="auto"``, why
    (serial, or a local cluster once the rows' measured cost paid for it).
    Falsy when a row failed.
    """

    rows: tuple
    out: Path
    summary: Path
    seconds: float
    where: str = ""

    @property
    def failed(self) -> list[RowResult]:
        return [r for r in self.rows if r.status == "failed"]

    def counts(self) -> dict:
        """``{"found": n, "not found": n, "failed": n, "reused": n}``."""
        out = {s: sum(r.status == s for r in self.rows) for s in ("found", "not found", "failed")}
        out["reused"] = sum(r.reused for r in self.rows)
        return out

    def __bool__(self) -> bool:
        return not self.failed

    def __len__(self) -> int:
        return len(self.rows)


def _status(record: dict) -> str:
    if "error" in record:
        return "failed"
    return "found" if record.get("success") else "not found"


def _row_result(task: Task, record: dict, path: Path, reused: bool) -> RowResult:
    return RowResult(task.row, task.name, _status(record), path, reused, record.get("error", ""), record)


def _finished(task: Task, path: Path) -> dict | None:
    """The earlier record of ``task`` at ``path`` if it is complete and of the same row."""
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(record, dict) or "error" in record or "success" not in record:
        return None
    made_from = record.get("batch", {}).get("task") if isinstance(record.get("batch"), dict) else None
    return record if made_from == json.loads(json.dumps(task.key())) else None


def _summary_row(r: RowResult, task: Task) -> list:
    rec = r.record
    support = rec.get("support")
    if support is None and isinstance(rec.get("motions"), list):
        support = sum(int(m.get("support", 0)) for m in rec["motions"])
    return [r.row, r.name, r.status, int(bool(rec.get("success"))), "" if support is None else support,
            "" if rec.get("rms") is None else rec["rms"], "" if rec.get("time_s") is None else rec["time_s"],
            task.source, task.target, task.seed, int(r.reused), r.error, r.path.name, *_verdict_cells(rec)]


def _verdict_cells(record: dict) -> list:
    """``verdict_support, verdict_chance, verdict_p`` of a record's ``info["verdict"]``; empty without one."""
    info = record.get("info")
    verdict = info.get("verdict") if isinstance(info, dict) else None
    if not isinstance(verdict, dict):
        return ["", "", ""]
    return ["" if verdict.get(key) is None else verdict[key] for key in ("support", "chance", "p_value")]


def _write_summary(path: Path, rows: Sequence[RowResult], tasks: Sequence[Task]) -> None:
    from .io import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(SUMMARY_HEADERS)
        for r, t in zip(rows, tasks):
            writer.writerow(_summary_row(r, t))


# ------------------------------------------------------------------ Dask
def _script_folders(fn: Callable) -> list[str]:
    """Folders the workers need on ``sys.path`` to run ``fn``: its script's, and ``sys.path[0]``."""
    folders = []
    module = sys.modules.get(getattr(fn, "__module__", "") or "")
    for f in (getattr(module, "__file__", None), getattr(sys.modules.get("__main__"), "__file__", None)):
        if f:
            folders.append(str(Path(f).resolve().parent))
    if sys.path and sys.path[0]:
        folders.append(str(Path(sys.path[0]).resolve()))
    return list(dict.fromkeys(folders))


def _cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS tells, else the count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _import_distributed():
    try:
        import distributed
    except ImportError as exc:
        msg = ("running on Dask needs dask.distributed: install the extra with "
               "`pip install 'gatv[distributed]'` (or use the serial scheduler).")
        raise InputError(msg) from exc
    return distributed


#: Dask settings of the local clusters :func:`connect` starts.  The first two
#: switch off diagnostics that cost CPU all the time a worker lives, taken from
#: the cores the rows run on: the statistical profiler of the dashboard's
#: "Profile" page (a sample of every worker's stack each 10 ms) and the
#: event-loop tick measurement, every 200 ms instead of 20 ms (it feeds the
#: "event loop unresponsive" warning, whose threshold is seconds, and a
#: dashboard metric); Dask's own test utilities run with the same two.  The
#: third keeps the nanny from setting ``MALLOC_TRIM_THRESHOLD_`` (65536) in the
#: workers' environment: an explicit trim threshold also fixes glibc's mmap
#: threshold at 128 KiB, so every larger numpy array is mapped and its pages
#: faulted in afresh, and a row ran 10–15% slower in a worker than here.  The
#: measurements are in docs/design-notes.md.
LOCAL_CLUSTER_CONFIG = {"distributed.worker.profile.enabled": False, "distributed.admin.tick.interval": "200ms",
                        "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}

#: Seconds of work one Dask task aims at when ``chunk`` is automatic: rows that
#: take less are grouped, so Dask's own cost per task (a few ms of scheduler,
#: worker and client time) stays near 1%.
TASK_SECONDS = 0.25


@contextlib.contextmanager
def connect(scheduler="local", *, workers: int | None = None, timeout: float = 10.0) -> Iterator:
    """A :class:`dask.distributed.Client` for ``scheduler``, closed on exit.

    Parameters
    ----------
    scheduler : "local", str or Client, default: "local"
        ``"local"`` starts a :class:`~dask.distributed.LocalCluster` of
        ``workers`` processes (default: one per core), one thread each,
        with numba limited to ``cores // workers`` threads; a string is the
        address of a running scheduler; a ``Client`` is yielded as it is
        (and not closed).
    workers : int, optional
        Worker processes of a local cluster.
    timeout : float, default: 10
        Seconds to wait for a remote scheduler.

    Raises
    ------
    InputError
        dask.distributed is not installed, ``workers`` is not a positive
        integer, or the scheduler cannot be reached (the message names it).
    """
    distributed = _import_distributed()
    if isinstance(scheduler, distributed.Client):
        yield scheduler
        return
    if scheduler in (None, "local"):
        import dask

        cores = _cores()
        n = check_int(workers, "workers", 1, allow_none=True) or cores
        threads = str(max(1, cores // n))
        env = {"NUMBA_NUM_THREADS": threads, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads,
               "OPENBLAS_NUM_THREADS": threads}
        # The scheduler reads the settings when it is made.  Each nanny hands its `config` to the
        # worker processes it starts, restarts included; by default that is a shallow copy of the
        # global config, whose nested values the `with` restores on exit, so give it a deep copy.
        with dask.config.set(LOCAL_CLUSTER_CONFIG):
            config = copy.deepcopy(dask.config.config)
            cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                               dashboard_address=":0", silence_logs=logging.ERROR, env=env,
                                               config=config)
        with cluster, distributed.Client(cluster) as client:
            yield client
        return
    if not isinstance(scheduler, str):
        msg = f"Expected `scheduler` to be 'local', 'serial', an address or a Client, got {scheduler!r}."
        raise InputError(msg)
    refused = _refused(scheduler, timeout)
    if refused is not None:  # nothing listens there: say so now rather than after `timeout`
        raise InputError(f"cannot reach the Dask scheduler at {scheduler!r} ({one_line(refused)}).")
    try:
        client = distributed.Client(scheduler, timeout=f"{timeout}s")
    except (OSError, TimeoutError, ValueError) as exc:
        msg = f"cannot reach the Dask scheduler at {scheduler!r} ({one_line(exc)})."
        raise InputError(msg) from exc
    try:
        yield client
    finally:
        client.close()


def _refused(address: str, timeout: float) -> OSError | None:
    """The error of a TCP connection to a ``tcp://host:port`` (or ``host:port``) scheduler that
    the host refused (nothing listens on the port), else None.

    A refused connection fails at once; Dask's client would retry it until
    its timeout.  Anything else (a host that does not answer, another
    protocol, a name that does not resolve) is left to Dask.
    """
    import socket
    from urllib.parse import urlsplit

    url = urlsplit(address if "://" in address else f"tcp://{address}")
    if url.scheme != "tcp":
        return None
    try:
        host, port = url.hostname, url.port
    except ValueError:
        return None
    if not host or port is None:
        return None
    try:
        with socket.create_connection((host, port), timeout=min(float(timeout), 2.0)):
            return None
    except ConnectionRefusedError as exc:
        return exc
    except OSError:
        return None


#: Seconds a local cluster costs before its first row on 2 cores: the cluster
#: (1.3 s) and each worker's imports and numba kernels from the cache (2.3 s,
#: the workers in parallel), measured on a shared 2-core machine.
LOCAL_START_SECONDS = 4.0
#: A local cluster is started only when it is expected to take at most this
#: share of the serial time left (estimates of a few rows are rough).
LOCAL_MARGIN = 0.8
#: Dask's own cost on a row's CPU time (scheduler, worker, serialisation).
LOCAL_OVERHEAD = 1.1
#: Rows that ``scheduler="auto"`` times on one numba thread (after the first,
#: which loads the kernels) before it settles on this process or a cluster.
MEASURED_ROWS = 3


@dataclass(frozen=True)
class StartDecision:
    """Whether a local cluster pays for the rows left (:func:`local_cluster_pays`) and why."""

    start: bool
    serial_s: float
    cluster_s: float
    why: str


def local_cluster_pays(timed: Sequence[tuple[float, float]], rows_left: int, workers: int) -> StartDecision:
    """Whether ``workers`` local single-threaded workers would finish the rows left sooner than this process.

    ``timed`` holds the ``(wall, CPU)`` seconds of rows run here on one
    numba thread, as a worker runs them.  Serially the rows left take their
    mean wall time each (at most that: this process runs them on every
    core's thread); on a cluster :data:`LOCAL_START_SECONDS`, then each
    worker's share of rows at their mean CPU time times
    :data:`LOCAL_OVERHEAD`.  The cluster must take at most
    :data:`LOCAL_MARGIN` of the serial time.
    """
    wall = sum(w for w, _ in timed) / max(len(timed), 1)
    cpu = sum(c for _, c in timed) / max(len(timed), 1)
    serial = wall * rows_left
    cluster = LOCAL_START_SECONDS + LOCAL_OVERHEAD * cpu * math.ceil(rows_left / max(workers, 1))
    start = workers > 1 and rows_left > 1 and cluster <= LOCAL_MARGIN * serial
    why = (f"{rows_left} rows left at {wall:.3g} s each: ~{serial:.3g} s here, ~{cluster:.3g} s on "
           f"{workers} local workers including ~{LOCAL_START_SECONDS:g} s to start them")
    return StartDecision(bool(start), serial, cluster, why)


def numba_plan(client) -> dict:
    """Numba threads for each worker of ``client``'s cluster: its host's cores over the worker
    threads on that host (at least 1), so that workers sharing a machine do not oversubscribe it."""
    workers = client.scheduler_info(n_workers=-1)["workers"]
    cores = client.run(_cores)
    on_host = collections.Counter()
    for info in workers.values():
        on_host[info.get("host")] += int(info.get("nthreads", 1))
    return {address: max(1, int(cores.get(address, 1)) // max(1, on_host[info.get("host")]))
            for address, info in workers.items()}


def _describe_client(scheduler, client) -> str:
    nthreads = client.nthreads()
    kind = "a local cluster" if scheduler in (None, "local") else f"the Dask scheduler at {client.scheduler.address}"
    return f"{kind} of {len(nthreads)} workers, {sum(nthreads.values())} threads"


def _threads(client) -> int:
    """Worker threads of the cluster behind ``client`` (at least 1: workers may join later)."""
    return max(1, sum(client.nthreads().values()))


def _rows_per_task(chunk: int | None, row_seconds: float | None, remaining: int, threads: int) -> int:
    """Rows of the next Dask task.

    A fixed ``chunk`` as given.  Automatic (``chunk`` None): one row until a
    task has finished, then as many rows as take about :data:`TASK_SECONDS`
    at the mean seconds per row so far, but never more than a
    ``2 * threads``-th of the rows left, so that the last tasks are small
    and the workers finish together.
    """
    if chunk:
        return chunk
    if row_seconds is None:
        return 1
    wanted = int(TASK_SECONDS / max(row_seconds, 1e-6))
    return max(1, min(wanted, remaining // (2 * threads)))


def _register_paths(client, fn: Callable) -> None:
    from ._dask import SysPath

    plugin = SysPath(_script_folders(fn))
    client.register_plugin(plugin, name=plugin.name)


def map_tasks(fn: Callable, tasks: Sequence, *, scheduler="local", workers: int | None = None,
              retries: int = 1, progress=None) -> list:
    """``[fn(task) for task in tasks]`` as Dask tasks, results in task order.

    Parameters
    ----------
    fn : callable
        Picklable (a module-level function; functions of a script run as
        ``__main__`` travel by value, and the script's folder is put on the
        workers' ``sys.path`` for its own imports).
    tasks : sequence
        Picklable arguments, one per call.
    scheduler : "local", "serial", str or Client, default: "local"
        See :func:`connect`; ``"serial"`` runs the list comprehension here.
    workers : int, optional
        Worker processes of a local cluster.
    retries : int, default: 1
        Re-runs of a task that raised (a killed worker's task is re-run by
        Dask regardless).
    progress : callable, optional
        ``progress(fraction, message)`` after each finished task.

    Returns
    -------
    list
        ``fn(task)`` for each task, in the order of ``tasks``.

    Raises
    ------
    Exception
        The first task's exception that persisted through its retries.
    """
    tasks = list(tasks)
    report = check_progress(progress)
    retries = check_int(retries, "retries", 0)
    if scheduler == "serial":
        out = []
        for k, task in enumerate(tasks):
            out.append(fn(task))
            report((k + 1) / max(len(tasks), 1), f"{k + 1}/{len(tasks)} tasks")
        return out
    distributed = _import_distributed()
    with connect(scheduler, workers=workers) as client:
        _register_paths(client, fn)
        futures = client.map(fn, tasks, pure=False, retries=retries)
        for done, future in enumerate(distributed.as_completed(futures), start=1):
            if future.status == "error":
                try:
                    future.result()  # raises the task's exception
                finally:
                    client.cancel([f for f in futures if f is not future])
            report(done / max(len(tasks), 1), f"{done}/{len(tasks)} tasks")
        return client.gather(futures)


# ------------------------------------------------------------------ batch
def run(pairs, out, *, command: str = "register", scheduler="auto", workers: int | None = None,
        seed: int = 0, defaults: Mapping | None = None, retries: int = 1, progress=None,
        timeout: float = 10.0, chunk: int | None = None) -> BatchResult:
    """Run ``command`` on every row of ``pairs``; one JSON per row in ``out``, and ``summary.csv``.

    Parameters
    ----------
    pairs : str, path-like or sequence of mappings
        The table of pairs (see :func:`read_pairs`).
    out : str or path-like
        Output folder, created when missing (only after every check passed).
        Row ``k`` is written to ``out/<name>.json`` (``name`` column, else
        ``row-0000k``); a motion found with a 4×4 matrix also to
        ``out/<name>.txt`` (:func:`gatv.io.write_matrix`, the text Open3D's
        examples load with ``numpy.loadtxt``).
    command : {"register", "segment", "instances", "nonrigid"}, default: "register"
    scheduler : "auto", "local", "serial", str or Client, default: "auto"
        Where the rows run (see the module docstring and :func:`connect`).
        ``"auto"``: here, one after the other; the second to
        :data:`MEASURED_ROWS` + 1-th rows on one numba thread, and when
        their cost says that a local cluster would finish the rest sooner
        including its start (:func:`local_cluster_pays`), the rest on one,
        else here on every thread;
        ``"local"`` starts one at once.  The result's ``where`` says which.
    workers : int, optional
        Worker processes of a local cluster; default one per core.
    seed : int, default: 0
        Seed of rows without a ``seed`` cell (as ``gatv register --seed``).
    defaults : mapping, optional
        Values of per-row options for rows that leave them empty.
    retries : int, default: 1
        Re-runs of a task that raised inside Dask.
    progress : callable, optional
        ``progress(fraction, message)`` after each row.
    timeout : float, default: 10
        Seconds to wait for a remote scheduler.
    chunk : int, optional
        Rows per Dask task.  Default: sized as the batch runs — one row per
        task until the first tasks finished, then as many rows as take
        about :data:`TASK_SECONDS` (short rows are grouped so that Dask's
        own cost per task stays small; long rows stay one per task), fewer
        towards the end.  ``chunk=1`` is one task per row.  The records do
        not depend on it; a chunk's rows are written when it finishes, and
        a lost worker's chunk is re-run whole.

    Returns
    -------
    BatchResult
        The rows in table order; falsy when a row failed.

    Raises
    ------
    InputError
        A bad table (no ``source``/``target`` column...), an unknown
        command, an unreachable scheduler, or an output folder that cannot
        be made.  Nothing is written then.

    Examples
    --------
    >>> import numpy as np, tempfile, os
    >>> from gatv import batch
    >>> from gatv.datasets import table2_trial
    >>> from gatv.io import write_points
    >>> folder = tempfile.mkdtemp()
    >>> trial = table2_trial(0.5, seed=1)
    >>> write_points(os.path.join(folder, "s.npy"), trial.source)
    >>> write_points(os.path.join(folder, "t.npy"), trial.target)
    >>> pairs = [{"source": os.path.join(folder, "s.npy"), "target": os.path.join(folder, "t.npy")}]
    >>> result = batch.run(pairs, os.path.join(folder, "out"), scheduler="serial")
    >>> result.counts()
    {'found': 1, 'not found': 0, 'failed': 0, 'reused': 0}
    """
    start = time.perf_counter()
    tasks = read_pairs(pairs, command=command, seed=seed, defaults=defaults)
    report = check_progress(progress)
    retries = check_int(retries, "retries", 0)
    chunk = check_int(chunk, "chunk", 1, allow_none=True)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: cannot write the batch there: not a folder.")
    paths = [out / f"{t.name}.json" for t in tasks]
    results: list[RowResult | None] = [None] * len(tasks)
    todo = []
    for k, (task, path) in enumerate(zip(tasks, paths)):
        earlier = _finished(task, path) if out.is_dir() else None
        if earlier is not None:
            results[k] = _row_result(task, earlier, path, reused=True)
        else:
            todo.append(k)
    done = len(tasks) - len(todo)

    def finish(k: int, record: dict) -> None:
        nonlocal done
        matrix = np.asarray(record.get("matrix", ()), dtype=float)
        if record.get("success") and matrix.shape == (4, 4):  # before the JSON, which marks the row done
            write_matrix(paths[k].with_suffix(".txt"), matrix)
        write_json(paths[k], record)
        results[k] = _row_result(tasks[k], record, paths[k], reused=False)
        done += 1
        report(done / len(tasks), f"{done}/{len(tasks)} rows")

    auto = scheduler == "auto"
    if auto:
        n_workers = check_int(workers, "workers", 1, allow_none=True) or _cores()
        try:
            import distributed  # noqa: F401
        except ImportError:  # without the extra, "auto" stays serial
            n_workers = 1
    where_ran = "serial" if scheduler == "serial" else ""
    with contextlib.ExitStack() as stack:
        # connect before writing anything: an unreachable scheduler leaves DIR untouched
        client = None
        if scheduler not in ("serial", "auto") and todo:
            client = stack.enter_context(connect(scheduler, workers=workers, timeout=timeout))
            where_ran = _describe_client(scheduler, client)
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{out}: cannot make the output folder ({exc.strerror or exc}).") from exc
        if done:
            report(done / len(tasks), f"{done}/{len(tasks)} rows (already done)")
        pending = collections.deque(todo)
        if auto and pending:
            # rows run here until their measured cost says that a local cluster pays for its start;
            # the measured rows run on one numba thread, as a worker's would
            timed = []  # (wall, CPU) seconds of the rows run here, the first (numba's cache) left out
            import numba

            threads_here = numba.get_num_threads()
            while pending:
                k = pending.popleft()
                measuring = n_workers > 1 and 1 <= len(timed) <= MEASURED_ROWS
                numba.set_num_threads(1 if measuring else threads_here)
                try:
                    w0, c0 = time.perf_counter(), time.process_time()
                    finish(k, compute(tasks[k]))
                    timed.append((time.perf_counter() - w0, time.process_time() - c0))
                finally:
                    numba.set_num_threads(threads_here)
                if not measuring:  # the first row also loads the numba kernels: not a measure
                    continue
                decision = local_cluster_pays(timed[1:], len(pending), n_workers)
                if pending and decision.start:
                    report(done / len(tasks), f"starting {n_workers} local workers: {decision.why}")
                    client = stack.enter_context(connect("local", workers=n_workers, timeout=timeout))
                    where_ran = (f"{len(timed)} rows here, then a local cluster of {n_workers} workers "
                                 f"({decision.why})")
                    break
                if len(timed) > MEASURED_ROWS:  # settled: the rest here, on every thread
                    break
            if client is None:
                whole = local_cluster_pays(timed[1:] or timed, max(len(todo) - 1, 1), n_workers)
                where_ran = ("serial, in this process: a local cluster would not have paid "
                             f"(after the first row, {whole.why})")
        if client is None:
            for k in pending:
                finish(k, compute(tasks[k]))
            pending.clear()
        if pending:
            distributed = _import_distributed()
            stamp = f"{os.getpid()}-{time.time_ns()}"
            where: dict = {}  # key of a task in flight -> its rows
            spent = [0.0, 0]  # seconds and rows of the tasks finished so far

            def submit():
                row_seconds = spent[0] / spent[1] if spent[1] else None
                size = _rows_per_task(chunk, row_seconds, len(pending), threads)
                ks = [pending.popleft() for _ in range(min(size, len(pending)))]
                first = tasks[ks[0]]
                future = client.submit(_compute_rows, tuple(tasks[k] for k in ks), plan, pure=False,
                                       retries=retries, key=f"gatv-{first.command}-{first.name}-{len(ks)}-{stamp}")
                where[future.key] = ks
                return future

            def fill(queue):
                # a fixed chunk: every task now; automatic: two per worker thread, sized as rows finish
                while pending and (chunk or len(where) < 2 * threads):
                    queue.add(submit())

            threads, counted = _threads(client), time.monotonic()
            plan = numba_plan(client)
            queue = distributed.as_completed()
            fill(queue)
            for future in queue:
                ks = where.pop(future.key)
                try:
                    records, seconds = future.result()
                    spent[0] += seconds
                    spent[1] += len(ks)
                except Exception as exc:  # noqa: BLE001 - KilledWorker past allowed-failures, cancelled...
                    records = [_lost(tasks[k], exc) for k in ks]
                future.release()
                for k, record in zip(ks, records):
                    finish(k, record)
                if pending:
                    if time.monotonic() - counted > 1.0:  # workers may have joined or left; ask the
                        threads, counted = _threads(client), time.monotonic()  # scheduler once a second
                        plan = numba_plan(client)
                    fill(queue)
    summary = out / "summary.csv"
    _write_summary(summary, results, tasks)
    return BatchResult(tuple(results), out, summary, time.perf_counter() - start,
                       where_ran or "nothing to run: every row was done")
