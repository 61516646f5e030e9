"""Test-suite settings.

Under CI (``CI`` set in the environment) hypothesis runs derandomized: the
same examples on every run, so a pass or a failure is reproducible.  Local
runs keep exploring new examples.
"""

from __future__ import annotations

import argparse
import os

import pytest
from hypothesis import settings

settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture
def parse_nonrigid():
    """``parse(argv)``: ``gatv nonrigid`` arguments as the CLI's own parser reads them."""
    from gatv.cli.nonrigid import add_parser

    def parse(argv):
        parser = argparse.ArgumentParser(prog="gatv")
        add_parser(parser.add_subparsers(dest="command"))
        return parser.parse_args(argv)

    return parse


# ------------------------------------------------------------ compile ahead
#: Kernels a cold run of the whole suite compiles, called once on tiny input through
#: the wrappers the product uses (so with the product's argument types), in the
#: order the suite first needs them: the congruent-triple search (test_batch), the
#: stick pass (test_catadioptric_motions), similar triples (test_peeling), the scans
#: pipeline's k-d tree and ICP kernels, the eigen solver (test_voting), and the ball pass last (test_affine2d, the first
#: file, compiles it itself).
_COMPILE_AHEAD = """
import numpy as np
from gatv.models.rigid.congruent import TargetIndex, trial_motions
from gatv.models.similarity import similar_trial_motions
from gatv.voting import vote
from gatv.voting._eigen import eig3_batch

rng = np.random.default_rng(0)
x = rng.uniform(-1.0, 1.0, (40, 3))
normals = rng.normal(size=(40, 3))
normals /= np.linalg.norm(normals, axis=1)[:, None]
index = TargetIndex(x, 0.05)
trial_motions(x, index, eps=0.01, max_triples=8, rng=rng, wide=2, sequential=True,
              source_normals=normals, target_normals=normals, max_enumerated=4)
vote(x, 0.3, normals, saliency=np.ones(40))  # the stick pass alone
similar_trial_motions(x, index, eps=0.01, max_triples=2, rng=rng)
from gatv._icp_kernels import (PARALLEL_BUILD, KDTree, local_heights, nearest_heights, neighbourhood_normals, plane_icp,
                               plane_icp_many, plane_icp_parallel, screen_icp)
from gatv.models.rigid.congruent import TargetGrid
tree = KDTree(x)
KDTree(rng.uniform(-1.0, 1.0, (PARALLEL_BUILD, 3)))  # the parallel build
local_heights(x, np.zeros(40, np.int64), x, normals, normals, np.zeros((40, 4), np.int64), 0.9)
plane_icp_many(x, tree.points, normals, *tree.nodes, np.eye(3)[None], np.zeros((1, 3)), np.array([0.3]), 2,
               np.array([1e-9]), np.array([0.0]))
tree.query(x, k=1, distance_upper_bound=0.1)
nearest_heights(x, np.flatnonzero(np.ones(40, bool)), normals, tree.points, *tree.nodes, 0.1)  # the output's rows
from gatv.candidates import one_to_one_rows
one_to_one_rows(np.array([0, 1, 0]), np.array([1.0, 0.5, 0.2]))  # the output's pairs
tree.query(x, k=16)
neighbourhood_normals(x, tree.query(x, k=12)[1], 12)
plane_icp(x, tree.points, normals, *tree.nodes, np.eye(3), np.zeros(3), 0.3, 2, 1e-9, 0.0)
plane_icp_parallel(x, tree.points, normals, *tree.nodes, np.eye(3), np.zeros(3), 0.3, 2, 1e-9, 0.0)
grid = TargetGrid.of(x, 0.1)
screen_icp(x, grid.target, grid.start, grid.order, grid.origin, grid.cell, grid.dims, np.eye(3)[None],
           np.zeros((1, 3)), 0.1, 2)
eig3_batch(np.zeros((2, 6)), np.empty((2, 3)), np.empty((2, 3, 3)))
vote(x, 0.3)
"""

#: Fewer collected tests than this (a file or a few) start no compilation ahead.
COMPILE_AHEAD_FROM = 200
# the commands' own compile-ahead (gatv.cli.warmup.compile_ahead) stays off in the suite, which
# compiles ahead its own way; tests of it set the variable themselves
os.environ.setdefault("GATV_COMPILE_AHEAD", "0")

_ahead: list = []


def pytest_collection_finish(session):
    """On a whole-suite run, compile the big kernels in a second process, beside the first tests.

    numba compiles on one core; on a cold cache (a fresh clone) the suite spends
    about 130 CPU-s compiling, most of it while the other core idles.  The
    process below fills numba's on-disk cache (the same ``NUMBA_CACHE_DIR``),
    from which the tests then load the kernels; a kernel a test reaches first is
    compiled there as before (numba writes cache files atomically).  On a warm
    cache it only loads them (a few CPU-s).  ``GATV_TEST_COMPILE_AHEAD=0``
    turns it off.
    """
    import subprocess
    import sys
    from pathlib import Path

    if os.environ.get("GATV_TEST_COMPILE_AHEAD", "1") == "0" or len(session.items) < COMPILE_AHEAD_FROM:
        return
    root = Path(__file__).resolve().parents[1]
    _ahead.append(subprocess.Popen([sys.executable, "-c", _COMPILE_AHEAD], cwd=root,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))


def pytest_sessionfinish(session, exitstatus):
    for proc in _ahead:
        if proc.poll() is None:
            proc.kill()
        proc.wait()


@pytest.fixture(scope="session")
def window_settings():
    """``window_settings(**overrides)``: :class:`gatv.nonrigid.stages.Settings` of a local non-rigid
    window (rigid local patches, growth on, no pre-alignment), the fields given overridden."""
    from gatv.nonrigid.stages import Settings

    def make(**kw):
        base = dict(seed=0, max_displacement=None, max_candidates=None, max_pairs=1_500_000, noise=None,
                    sigma=None, n_stick_passes=3, structure="auto", strain=0.35, gate=None, smoothing=None,
                    neighbours=8, grow=True, prealign=False, memory_budget=None, model="rigid", local=True,
                    parts=False)
        base.update(kw)
        return Settings(**base)

    return make
