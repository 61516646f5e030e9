"""``gatv warmup``: compile the numba kernels once, ahead of the first real run.

gatv's kernels are numba functions cached on disk (``cache=True``): the
first call of a fresh install compiles them (one to two minutes on a
laptop), every later run loads them in a fraction of a second.  ``gatv
warmup`` runs small problems that reach every kernel of the registration
pipelines, in parallel processes, so that the first ``gatv demo`` or
``gatv register`` starts at full speed.  ``make demo`` runs it after
installing.

While a command compiles, its progress output says ``compiling kernels
(first run only)`` (:func:`compile_notes`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from ._common import EXIT_OK, PROG, add_verbosity, guarded

__all__ = ["COMPILING", "NAME", "PARTS", "add_parser", "compile_notes", "run", "run_part"]

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
def compile_notes(progress=None, *, quiet: bool = False):
    """While the block runs, say ``compiling kernels (first run only)`` when numba compiles.

    Yields a listener: ``progress``, the callback to hand to the work (it
    remembers the last fraction reported; None without ``progress``),
    ``count`` (kernels compiled, nested ones not counted) and ``seconds``
    (spent compiling).  Each compilation sends ``progress`` the note and
    the kernel's name at the last fraction reported; without ``progress``
    one line goes to stderr the first time (none with ``quiet``).  Nothing
    is said when every kernel comes from the cache.
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
        yield listener


# ---------------------------------------------------------------- the parts
def _voting():
    """Ball and stick passes on a dense sampled surface (gatv.voting)."""
    from ..voting import extract_surfaces

    rng = np.random.default_rng(0)
    u, v = rng.uniform(0, 2 * np.pi, (2, 3000))
    pts = np.c_[(2 + np.cos(v)) * np.cos(u), (2 + np.cos(v)) * np.sin(u), np.sin(v)]
    extract_surfaces(np.r_[pts, rng.uniform(-3, 3, (300, 3))])


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


#: The parts of a warmup, in the order one process would run them.
PARTS = {"voting": _voting, "exact": _exact, "scans": _scans}
#: How the parts are shared out among processes: the exact pipeline spends its
#: first tens of seconds on the congruent kernels, by when the voting part has
#: put the voting kernels in the cache.
_JOBS = (("exact",), ("voting", "scans"))


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

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    jobs = args.jobs if args.jobs is not None else min(2, cores)
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
