"""The first run of a fresh install (issue 42): it says that it compiles, and ``gatv warmup``
compiles ahead so that the first ``gatv demo`` starts at full speed."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from numba import njit

from gatv import cli
from gatv.cli.warmup import COMPILING, compile_notes


def _fresh_kernel():
    @njit  # not cached: compiles on its first call in every process
    def twice(x):
        return 2.0 * x

    return twice


def test_compile_notes_say_compiling_while_numba_compiles():
    said = []
    kernel = _fresh_kernel()
    with compile_notes(lambda f, m="": said.append((f, m))) as notes:
        notes.progress(0.25, "started")
        assert kernel(np.ones(3)).sum() == 6.0
    assert notes.count == 1 and notes.seconds > 0
    assert said[0] == (0.25, "started")
    assert said[1][0] == 0.25 and said[1][1].startswith(COMPILING) and "twice" in said[1][1]
    said.clear()
    with compile_notes(lambda f, m="": said.append((f, m))) as notes:
        kernel(np.ones(3))  # compiled already: nothing to say
    assert notes.count == 0 and said == []


def test_compile_notes_without_progress_print_one_line(capsys):
    with compile_notes(None) as notes:
        _fresh_kernel()(1.0)
        _fresh_kernel()(1.0)
    assert notes.progress is None and notes.count == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and COMPILING in err[0] and "gatv warmup" in err[0]
    with compile_notes(None, quiet=True):
        _fresh_kernel()(1.0)
    assert capsys.readouterr().err == ""


def test_warmup_is_a_command_with_bad_input_exit_2(capsys):
    assert cli.main(["warmup", "--jobs", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--jobs" in err[0]


def _gatv(args, cache, timeout=900):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYVISTA_OFF_SCREEN="true", GATV_COMPILE_AHEAD="1")
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "gatv", *args], env=env, capture_output=True, text=True,
                          timeout=timeout)
    return proc, time.perf_counter() - start


@pytest.mark.slow
def test_first_demo_after_warmup_starts_at_full_speed(tmp_path):
    """Empty numba cache: `gatv warmup`, then `gatv demo` compiles nothing.

    (Without the warmup, the first demo says it compiles; its time is
    measured by benchmarks/batch.py.)"""
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    proc, _ = _gatv(["warmup"], cache)
    assert proc.returncode == 0, proc.stderr
    assert "done in" in proc.stdout
    proc, _ = _gatv(["demo", "--progress", "--out", str(tmp_path / "r.json")], cache)
    assert proc.returncode == 0, proc.stderr
    assert COMPILING not in proc.stderr


@pytest.mark.slow
def test_first_register_says_it_compiles(tmp_path):
    from gatv.datasets import table2_trial
    from gatv.io import write_points

    trial = table2_trial(0.5, seed=4)
    write_points(tmp_path / "s.npy", trial.source)
    write_points(tmp_path / "t.npy", trial.target)
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    proc, _ = _gatv(["register", str(tmp_path / "s.npy"), str(tmp_path / "t.npy"), "--progress"], cache)
    assert proc.returncode == 0, proc.stderr
    assert f"] {COMPILING}: " in proc.stderr


@pytest.mark.slow
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="compiles ahead only with two cores")
def test_first_demo_compiles_ahead_then_never_again(tmp_path):
    """A fresh install's first demo compiles in two processes before it runs; the next compiles nothing."""
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    proc, _ = _gatv(["demo", "--progress", "--out", str(tmp_path / "r.json")], cache)
    assert proc.returncode == 0, proc.stderr
    assert f"] {COMPILING}, 2 processes" in proc.stderr
    assert "precision 1.000, recall 1.000" in proc.stdout
    proc, _ = _gatv(["demo", "--progress", "--out", str(tmp_path / "r2.json")], cache)
    assert proc.returncode == 0, proc.stderr
    assert COMPILING not in proc.stderr


def test_compile_ahead_only_on_a_cold_cache_and_two_cores(monkeypatch):
    """Nothing is spawned when the cache holds the kernels, on one core, or when turned off."""
    from gatv.cli import warmup

    said = []
    monkeypatch.setenv("GATV_COMPILE_AHEAD", "0")
    monkeypatch.setattr(warmup, "kernels_cached", lambda: False)
    assert warmup.compile_ahead(lambda f, m="": said.append(m)) is False
    monkeypatch.setenv("GATV_COMPILE_AHEAD", "1")
    monkeypatch.setattr(warmup, "kernels_cached", lambda: True)
    assert warmup.compile_ahead(lambda f, m="": said.append(m)) is False
    monkeypatch.setattr(warmup, "kernels_cached", lambda: False)
    monkeypatch.setattr(warmup, "_cores", lambda: 1)
    assert warmup.compile_ahead(lambda f, m="": said.append(m)) is False
    assert said == []


def test_kernels_cached_is_false_on_an_empty_cache_and_true_after_a_search(tmp_path):
    """An empty NUMBA_CACHE_DIR reads as a fresh install; this process's cache, after a search, does not."""
    from gatv.cli.warmup import kernels_cached
    from gatv.datasets import table2_trial
    from gatv.registration import register

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"))
    proc = subprocess.run([sys.executable, "-c", "from gatv.cli.warmup import kernels_cached; print(kernels_cached())"],
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False"]
    trial = table2_trial(0.5, seed=1)
    assert register(trial.source, trial.target, seed=0)
    assert kernels_cached() is True


def test_progress_bar_shows_no_time_left_while_compiling(monkeypatch):
    """The frozen bar said 1:50:46 left while numba compiled: no estimate while compiling."""
    import io

    from gatv.cli._common import ProgressBar

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    bar = ProgressBar()
    bar(0.01, "tolerance 1e-06: 2 triples")
    assert "{remaining}" in bar.bar.bar_format
    bar(0.01, f"{COMPILING}: triple_hypotheses")
    assert "{remaining}" not in bar.bar.bar_format and "{elapsed}" in bar.bar.bar_format
    bar(0.5, "tolerance 0.01: 40 triples")
    assert "{remaining}" in bar.bar.bar_format
    bar.close()
