"""``gatv warmup``: compile the numba kernels once, ahead of the first real run.

gatv's kernels are numba functions cached on disk (``cache=True``): the
first call of a fresh install compiles them (one to two minutes on a
laptop), every later run loads them in a fraction of a second.  ``gatv
warmup`` runs small problems that reach every kernel of the registration
pipelines, in parallel processes, so that the first ``gatv demo`` or
``gatv register`` starts at full speed.  ``make demo`` runs it after
installing.

While a command compiles, its progress output says ``compiling kernels
(first run only)`` (:func:`compile_notes`).  On a fresh install's first
run, the commands that register (``demo``, ``register``, ``segment``,
``instances``, ``track``) compile ahead as ``gatv warmup`` does, on two
cores at once, before they start (:func:`compile_ahead`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from ._common import EXIT_OK, PROG, add_verbosity, guarded

__all__ = [
    "COMPILING", "NAME", "PARTS", "add_parser", "compile_ahead", "compile_notes", "kernels_cached", "run",
    "run_part",
]

NAME = "warmup"
#: What the progress output says while numba compiles.
COMPILING = "compiling kernels (first run only)"


# -------------------------------------------------------- compile reports
class _Listener:
    """Counts numba compilations and reports each one's start."""

    def __init__(self, report=None):
        self.report = report
        self.count = 0
        self.seconds = 0.0
        self._start: list[float] = []

    def on_start(self, event):
        self._start.append(time.perf_counter())
        if len(self._start) == 1:  # the outermost kernel, not every function it calls
            self.count += 1
            if self.report is not None:
                name = getattr(event.data.get("dispatcher"), "__name__", "")
                self.report(name)

    def on_end(self, event):
        t0 = self._start.pop() if self._start else time.perf_counter()
        if not self._start:
            self.seconds += time.perf_counter() - t0


@contextlib.contextmanager
def compile_notes(progress=None, *, quiet: bool = False, ahead: bool = False):
    """While the block runs, say ``compiling kernels (first run only)`` when numba compiles.

    Yields a listener: ``progress``, the callback to hand to the work (it
    remembers the last fraction reported; None without ``progress``),
    ``count`` (kernels compiled, nested ones not counted) and ``seconds``
    (spent compiling).  Each compilation sends ``progress`` the note and
    the kernel's name at the last fraction reported; without ``progress``
    one line goes to stderr the first time (none with ``quiet``).  Nothing
    is said when every kernel comes from the cache.

    With ``ahead``, a fresh install's kernels are first compiled on two
    cores at once (:func:`compile_ahead`), and the block then runs at full
    speed.
    """
    from numba.core import event

    state = {"fraction": 0.0, "said": False}

    def report(name):
        if progress is not None:
            progress(state["fraction"], f"{COMPILING}: {name}")
        elif not quiet and not state["said"]:
            print(f"{PROG}: {COMPILING}; later runs start at once (`{PROG} warmup` does this ahead)",
                  file=sys.stderr, flush=True)
        state["said"] = True

    listener = _Listener(report)
    if progress is not None:
        def tracking(fraction, message=""):
            state["fraction"] = fraction
            progress(fraction, message)

        listener.progress = tracking
    else:
        listener.progress = None

    class _Relay(event.Listener):
        def on_start(self, ev):
            listener.on_start(ev)

        def on_end(self, ev):
            listener.on_end(ev)

    with event.install_listener("numba:compile", _Relay()):
        if ahead:
            compile_ahead(listener.progress)
        yield listener


# ---------------------------------------------------------------- the parts
def _torus(n=3000, clutter=300):
    """Points on a torus and uniform clutter about it."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    pts = np.c_[(2 + np.cos(v)) * np.cos(u), (2 + np.cos(v)) * np.sin(u), np.sin(v)]
    return np.r_[pts, rng.uniform(-3, 3, (clutter, 3))]


def _ball():
    """One sparse ball pass (gatv.voting.vote), the only voting the exact pipeline does."""
    from ..voting import vote

    vote(_torus())


def _voting():
    """Ball and stick passes on a dense sampled surface (gatv.voting)."""
    from ..voting import extract_surfaces

    extract_surfaces(_torus())


def _exact():
    """The exact pipeline on the demo's problem (congruent triples, fits, voting)."""
    from ..datasets import demo_mesh, synthetic_trial
    from ..registration import register

    mesh = demo_mesh("ant")
    trial = synthetic_trial(0.5, inliers=mesh, max_translation=float(np.ptp(mesh, axis=0).max()), seed=1)
    register(trial.source, trial.target, seed=0)


def _scans():
    """The scans pipeline on two overlapping views of a dense surface."""
    from ..datasets import random_rotation
    from ..registration import register

    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 2 * np.pi, (2, 6000))
    surf = np.c_[(2 + np.cos(v)) * np.cos(u), (2 + np.cos(v)) * np.sin(u) * 1.3, np.sin(v) + 0.3 * np.cos(3 * u)]
    a, b = surf[surf[:, 0] > -1.0], surf[surf[:, 0] < 1.0]
    R = random_rotation(rng, (10.0, 30.0))
    register(a, b @ R.T + 0.5, seed=0, pipeline="scans")
    # Real scans' k-d trees are built in parallel from PARALLEL_BUILD points (these views are smaller).
    from .._icp_kernels import PARALLEL_BUILD, KDTree

    KDTree(rng.uniform(-1.0, 1.0, (PARALLEL_BUILD, 3)))


#: The parts of a warmup, in the order one process would run them.
PARTS = {"ball": _ball, "voting": _voting, "exact": _exact, "scans": _scans}
#: How the parts are shared out among processes: the exact pipeline spends its
#: first tens of seconds on the congruent kernels, by when the voting part has
#: put the voting kernels in the cache.
_JOBS = (("exact",), ("voting", "scans"))


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def kernels_cached() -> bool:
    """Whether numba's cache holds the congruent-triple kernels of this source (False on a fresh install).

    Reads the cache index of
    :func:`gatv.models.rigid.congruent_kernels.triple_hypotheses`, the
    kernel that takes longest to compile; an index written for other
    sources counts as empty.  True when it cannot tell.
    """
    try:
        from ..models.rigid.congruent_kernels import triple_hypotheses

        return bool(triple_hypotheses._cache._cache_file._load_index())
    except Exception:  # numba's cache layout is not public: compile as the run goes
        return True


def compile_ahead(progress=None) -> bool:
    """On a fresh install, compile the registration kernels on two cores at once; True if it did.

    The first run of a command otherwise compiles its kernels one after
    another as the pipeline reaches them (about 30 s of CPU for the exact
    pipeline, all on one core).  When :func:`kernels_cached` says the cache
    is empty and the machine has two cores or more, the ``exact`` part runs
    in a second process (congruent triples first, about two thirds of the
    CPU) while this one runs ``ball``, the voting kernels, which the second
    process then finds in numba's cache.  The command then loads every
    kernel the exact pipeline needs (the scans pipeline compiles its stick
    pass as it goes).  A part that fails is left to the command to compile.
    ``GATV_COMPILE_AHEAD=0`` in the environment turns it off (the test
    suite compiles ahead its own way).
    """
    if os.environ.get("GATV_COMPILE_AHEAD", "1") == "0" or _cores() < 2 or kernels_cached():
        return False
    import multiprocessing

    if progress is not None:
        progress(0.0, f"{COMPILING}, 2 processes")
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        other = pool.submit(run_part, ("exact",))
        with contextlib.suppress(Exception):
            run_part(("ball",))
        with contextlib.suppress(Exception):
            other.result()
    return True


def run_part(names) -> list[tuple[str, float, int]]:
    """Run warmup parts in this process: ``(name, seconds, kernels compiled)`` for each."""
    out = []
    for name in names:
        with compile_notes(quiet=True) as listener:
            start = time.perf_counter()
            PARTS[name]()
        out.append((name, time.perf_counter() - start, listener.count))
    return out


def add_parser(subparsers):
    """Add the ``warmup`` subcommand to an ``argparse`` subparsers object."""
    p = subparsers.add_parser(
        NAME,
        help="compile the numba kernels now, so that the first real run starts at full speed",
        description=(
            "Compile and cache gatv's numba kernels by running small problems through the exact "
            "and the scans pipelines (and tensor voting), in parallel processes. A fresh install "
            "otherwise compiles them during its first run (one to two minutes); the cache lives "
            "beside the installed package, or in NUMBA_CACHE_DIR."
        ),
    )
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="processes (default: 2, or 1 on a one-core machine)")
    add_verbosity(p, progress=False)
    p.set_defaults(handler=run)
    return p


@guarded
def run(args) -> int:
    """Run ``gatv warmup`` on parsed ``args``; return the exit status."""
    from ._common import UsageError

    jobs = args.jobs if args.jobs is not None else min(2, _cores())
    if jobs < 1:
        raise UsageError(f"expected --jobs >= 1, got {jobs}.")
    groups = [tuple(n for g in _JOBS for n in g)] if jobs == 1 else list(_JOBS)
    if not args.quiet:
        print(f"{PROG} warmup: {COMPILING}, {len(groups)} process{'es' if len(groups) > 1 else ''} ...",
              flush=True)
    start = time.perf_counter()
    if len(groups) == 1:
        results = [run_part(groups[0])]
    else:
        import multiprocessing

        with ProcessPoolExecutor(len(groups), mp_context=multiprocessing.get_context("spawn")) as pool:
            results = list(pool.map(run_part, groups))
    if not args.quiet:
        for name, seconds, count in (r for group in results for r in group):
            print(f"  {name:<7} {seconds:6.1f} s, {count} kernel{'s' if count != 1 else ''} compiled")
        print(f"{PROG} warmup: done in {time.perf_counter() - start:.1f} s")
    return EXIT_OK
