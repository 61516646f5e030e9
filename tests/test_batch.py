"""gatv.batch and `gatv batch`: rows as Dask tasks equal the serial results, bad rows are
recorded while the others finish, a killed worker loses no row, a second run resumes."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from gatv import batch, cli
from gatv.datasets import table2_trial
from gatv.errors import InputError
from gatv.io import read_matrix, write_points

distributed = pytest.importorskip("distributed")

N_ROWS = 4


def _record_without_times(record: dict) -> dict:
    out = dict(record)
    out.pop("time_s", None)
    info = dict(out.get("info") or {})
    info.pop("time_s", None)
    out["info"] = info
    return out


@pytest.fixture(scope="module")
def client():
    """One local cluster of two single-threaded workers for the module (startup is the slow part)."""
    with batch.connect("local", workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    """Small Table-2 pairs (20 inliers, f = 0.5) written as .npy, .xyz and .pcd; the trials."""
    folder = tmp_path_factory.mktemp("pairs")
    trials, rows = [], []
    for k in range(N_ROWS):
        trial = table2_trial(0.5, n_inliers=20, seed=100 + k)
        ext = (".npy", ".xyz", ".npy", ".pcd")[k]
        write_points(folder / f"s{k}{ext}", trial.source, double=True)
        write_points(folder / f"t{k}{ext}", trial.target, double=True)
        trials.append(trial)
        rows.append({"source": f"s{k}{ext}", "target": f"t{k}{ext}", "seed": str(k)})
    return folder, trials, rows


def _write_csv(path, rows, columns=("source", "target", "seed")):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        for r in rows:
            w.writerow({c: r.get(c, "") for c in columns})
    return path


def test_local_cluster_equals_serial(tmp_path, pair_files, client):
    folder, trials, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    serial = batch.run(table, tmp_path / "serial", scheduler="serial")
    dask = batch.run(table, tmp_path / "dask", scheduler=client)
    assert serial and dask
    assert [r.status for r in dask.rows] == ["found"] * N_ROWS
    for a, b, trial in zip(serial.rows, dask.rows, trials):
        on_disk = json.loads(b.path.read_text())
        assert _record_without_times(on_disk) == _record_without_times(json.loads(a.path.read_text()))
        # the schema of `gatv register --out`, with the paths, the 4x4 matrix and the true motion
        assert on_disk["source"] == str(folder / rows[a.row]["source"])
        assert on_disk["seed"] == a.row and on_disk["success"] is True
        m = np.asarray(on_disk["matrix"])
        np.testing.assert_allclose(m[:3, :3], trial.rotation, atol=1e-6)
        np.testing.assert_allclose(m[:3, 3], trial.translation, atol=1e-6)
        np.testing.assert_array_equal(read_matrix(b.path.with_suffix(".txt")), m)
        pairs = {tuple(p) for p in on_disk["correspondences"]}
        assert {tuple(p) for p in trial.true_pairs} <= pairs
    with open(dask.summary, newline="") as fh:
        summary = list(csv.DictReader(fh))
    assert [s["name"] for s in summary] == [f"row-{k:05d}" for k in range(N_ROWS)]
    assert {s["status"] for s in summary} == {"found"} and {s["reused"] for s in summary} == {"0"}


def test_batch_equals_the_register_command(tmp_path, pair_files):
    """A row's JSON is `gatv register --out`'s record plus the batch block."""
    folder, _, rows = pair_files
    src, tgt = str(folder / rows[0]["source"]), str(folder / rows[0]["target"])
    result = batch.run([{"source": src, "target": tgt}], tmp_path / "b", scheduler="serial", seed=0)
    out = tmp_path / "one.json"
    assert cli.main(["register", src, tgt, "--seed", "0", "--out", str(out), "-q"]) == 0
    single = _record_without_times(json.loads(out.read_text()))
    row = _record_without_times(json.loads(result.rows[0].path.read_text()))
    assert row.pop("batch")["row"] == 0
    assert row == single


def test_corrupt_rows_are_recorded_and_the_others_finish(tmp_path, pair_files, client, capsys):
    folder, _, rows = pair_files
    np.save(folder / "nan.npy", np.where(np.eye(30, 3) > 0, np.nan, 1.0))
    np.save(folder / "flat.npy", np.ones((30, 2)))
    bad = [
        {"source": "missing.npy", "target": rows[0]["target"]},
        {"source": "nan.npy", "target": rows[0]["target"]},
        {"source": "flat.npy", "target": rows[0]["target"]},
        {"source": rows[0]["source"], "target": rows[0]["target"], "seed": "x"},
    ]
    table = _write_csv(tmp_path / "pairs.csv", [{**r, "source": str(folder / r["source"]),
                                                  "target": str(folder / r["target"])}
                                                 for r in [rows[1], *bad, rows[2]]])
    out = tmp_path / "out"
    status = cli.main(["batch", str(table), "--out", str(out), "--scheduler", client.scheduler.address, "-q"])
    assert status == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "4 of 6 rows failed" in err[0]
    records = [json.loads((out / f"row-{k:05d}.json").read_text()) for k in range(6)]
    assert [r["success"] for r in records] == [True, False, False, False, False, True]
    assert "no such file" in records[1]["error"]
    assert "NaN" in records[2]["error"] and records[2]["error_type"] == "PointFileError"
    assert "3 columns" in records[3]["error"]
    assert "`seed`" in records[4]["error"] and "integer" in records[4]["error"]
    assert not (out / "row-00001.txt").exists() and (out / "row-00005.txt").exists()
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_second_run_skips_finished_rows(tmp_path, pair_files):
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    out = tmp_path / "out"
    first = batch.run(table, out, scheduler="serial")
    stamps = {r.name: r.path.stat().st_mtime_ns for r in first.rows}
    again = batch.run(table, out, scheduler="serial")
    assert again.counts() == {"found": N_ROWS, "not found": 0, "failed": 0, "reused": N_ROWS}
    assert {r.name: r.path.stat().st_mtime_ns for r in again.rows} == stamps
    # a lost JSON and a changed seed are run again; the others are kept
    first.rows[1].path.unlink()
    changed = [dict(r) for r in rows]
    changed[2]["seed"] = "7"
    third = batch.run(_write_csv(tmp_path / "changed.csv", [{**r, "source": str(folder / r["source"]),
                                                              "target": str(folder / r["target"])}
                                                             for r in changed]), out, scheduler="serial")
    assert [r.reused for r in third.rows] == [True, False, False, True]
    assert json.loads(third.rows[2].path.read_text())["seed"] == 7


@pytest.mark.parametrize("chunk", [None, 2])
def test_killed_worker_loses_no_row(tmp_path, pair_files, client, chunk):
    """Kill a worker process while the batch runs: its task (one row, or a chunk of rows) is re-run
    elsewhere and every row lands."""
    folder, _, rows = pair_files
    many = [{**rows[k % N_ROWS], "name": f"r{k}", "seed": str(k)} for k in range(8)]
    table = _write_csv(folder / "many.csv", many, columns=("name", "source", "target", "seed"))
    before = client.run(os.getpid)
    killed = []

    def kill_one(fraction, message=""):
        if not killed:  # after the first row: both workers are busy with the next ones
            pid = min(client.run(os.getpid).items())[1]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    result = batch.run(table, tmp_path / "out", scheduler=client, progress=kill_one, chunk=chunk)
    assert killed and result.counts()["found"] == 8 and result
    assert sorted(p.name for p in (tmp_path / "out").glob("*.json")) == sorted(f"r{k}.json" for k in range(8))
    client.wait_for_workers(2, timeout=60)
    assert killed[0] not in client.run(os.getpid).values() and killed[0] in before.values()
    # the nanny starts the new worker with the local cluster's settings (no profiler)
    assert set(client.run(_profiler_enabled).values()) == {False}
    serial = batch.run(table, tmp_path / "serial", scheduler="serial")
    for a, b in zip(serial.rows, result.rows):
        assert _record_without_times(a.record) == _record_without_times(b.record)


def _profiler_enabled() -> bool:
    import dask

    return dask.config.get("distributed.worker.profile.enabled")


# ----------------------------------------------------------------- bad input
def _one_error(capsys, *fragments):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for f in fragments:
        assert f in err[0]


def test_table_without_columns_is_exit_2(tmp_path, capsys):
    table = tmp_path / "pairs.csv"
    table.write_text("from,to\na.npy,b.npy\n")
    out = tmp_path / "out"
    assert cli.main(["batch", str(table), "--out", str(out), "--scheduler", "serial"]) == 2
    _one_error(capsys, "`source`", "`target`")
    assert not out.exists()
    table.write_text("source,target,max_angel\na.npy,b.npy,5\n")
    assert cli.main(["batch", str(table), "--out", str(out)]) == 2
    _one_error(capsys, "max_angel", "max_angle")
    table.write_text("source,target\n")
    assert cli.main(["batch", str(table), "--out", str(out)]) == 2
    _one_error(capsys, "no rows")
    assert cli.main(["batch", str(tmp_path / "absent.csv"), "--out", str(out)]) == 2
    _one_error(capsys, "absent.csv")
    assert not out.exists()


def test_unknown_command_is_exit_2(tmp_path, pair_files, capsys):
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    out = tmp_path / "out"
    assert cli.main(["batch", str(table), "--out", str(out), "--command", "warp"]) == 2
    _one_error(capsys, "--command", "warp")
    with pytest.raises(InputError, match="`command`"):
        batch.run(table, out, command="warp", scheduler="serial")
    assert not out.exists()


def test_unreachable_scheduler_is_exit_2(tmp_path, pair_files, capsys):
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    out = tmp_path / "out"
    status = cli.main(["batch", str(table), "--out", str(out), "--scheduler", "tcp://127.0.0.1:9",
                       "--connect-timeout", "1"])
    assert status == 2
    _one_error(capsys, "cannot reach the Dask scheduler", "tcp://127.0.0.1:9")
    assert not out.exists()


def test_read_pairs_options_and_defaults(tmp_path):
    table = tmp_path / "p.csv"
    table.write_text("Source,Target,max-angle,model,name\nsub/a.npy,/abs/b.npy,5,similarity,first\n"
                     "c.npy,d.npy,,,\n")
    tasks = batch.read_pairs(table, seed=3, defaults={"model": "rigid", "noise": "0.01"})
    assert tasks[0].source == str(tmp_path / "sub" / "a.npy") and tasks[0].target == "/abs/b.npy"
    assert tasks[0].name == "first" and tasks[1].name == "row-00001"
    assert dict(tasks[0].options) == {"max_angle": 5.0, "model": "similarity", "noise": 0.01}
    assert dict(tasks[1].options) == {"model": "rigid", "noise": 0.01}
    assert tasks[0].seed == tasks[1].seed == 3
    with pytest.raises(InputError, match="same name"):
        batch.read_pairs([{"source": "a", "target": "b", "name": "x"}] * 2)
    with pytest.raises(InputError, match="unknown option"):
        batch.read_pairs([{"source": "a", "target": "b"}], defaults={"angle": 1})
    bad = batch.read_pairs([{"source": "a", "target": "b", "noise": "nan"}])
    assert "noise" in bad[0].problem


def test_map_tasks_runs_a_scripts_functions(tmp_path):
    """A script run as `python x.py` maps its own functions, which import a helper beside it."""
    (tmp_path / "helper_mod.py").write_text("def square(x):\n    return x * x\n")
    (tmp_path / "script.py").write_text(textwrap.dedent("""
        import sys
        from helper_mod import square
        from gatv.batch import map_tasks

        def job(x):
            return square(x) + 1

        if __name__ == "__main__":
            print(map_tasks(job, [3, 1, 2], scheduler="local", workers=1))
    """))
    done = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=180, env={**os.environ, "PYTHONPATH": ""}, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[10, 2, 5]"


def test_map_tasks_serial_and_errors(client):
    assert batch.map_tasks(abs, [-1, 2, -3], scheduler="serial") == [1, 2, 3]
    assert batch.map_tasks(abs, [-1, 2, -3], scheduler=client) == [1, 2, 3]
    with pytest.raises(TypeError):
        batch.map_tasks(abs, [-1, "x"], scheduler=client, retries=0)


def test_progress_reaches_one(tmp_path, pair_files):
    folder, _, rows = pair_files
    seen = []
    batch.run([{**r, "source": str(folder / r["source"]), "target": str(folder / r["target"])} for r in rows[:2]],
              tmp_path / "o", scheduler="serial", progress=lambda f, m="": seen.append((f, m)))
    assert [f for f, _ in seen] == [0.5, 1.0] and seen[-1][1] == "2/2 rows"


def test_progress_bar_on_a_terminal(monkeypatch, capsys):
    """A tty gets a tqdm bar (closed at 100%); --quiet silences it; --progress prints lines when piped."""
    from argparse import Namespace

    from gatv.cli._common import ProgressBar, ProgressLines, progress_printer

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    bar = progress_printer(Namespace(quiet=False, progress=False), total=4, unit="row")
    assert isinstance(bar, ProgressBar)
    bar(0.5, "2/4 rows")
    assert bar.bar.n == 2
    bar(1.0)
    assert bar.bar is None
    assert progress_printer(Namespace(quiet=True, progress=False)) is None
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False, raising=False)
    assert progress_printer(Namespace(quiet=False, progress=False)) is None
    assert isinstance(progress_printer(Namespace(quiet=False, progress=True)), ProgressLines)


def test_segment_rows_take_their_options(tmp_path, pair_files):
    """`--command segment`: per-row options reach gatv.motions.segment; the summary counts support."""
    folder, trials, rows = pair_files
    table = [{"source": str(folder / rows[0]["source"]), "target": str(folder / rows[0]["target"]),
              "max_motions": "1"}]
    result = batch.run(table, tmp_path / "seg", command="segment", scheduler="serial")
    record = result.rows[0].record
    assert result and record["options"] == {"max_motions": 1} and record["n_motions"] == 1
    m = np.asarray(record["motions"][0]["matrix"])
    np.testing.assert_allclose(m[:3, :3], trials[0].rotation, atol=1e-6)
    with open(result.summary, newline="") as fh:
        (line,) = list(csv.DictReader(fh))
    assert int(line["support"]) == record["motions"][0]["support"] >= 20
    assert not (tmp_path / "seg" / "row-00000.txt").exists()  # a segmentation has no single matrix


# ------------------------------------------------------------- rows per task
def _gatv_tasks(stream) -> list[str]:
    return sorted({t["key"] for t in stream.data if str(t["key"]).startswith("gatv-")})


@pytest.mark.parametrize("chunk", [3, None])
def test_rows_grouped_into_tasks_equal_serial(tmp_path, pair_files, client, chunk, monkeypatch):
    """Many short rows: a fixed chunk makes ceil(n / chunk) tasks; the automatic size groups rows
    once the first tasks timed them; either way every row lands once, equal to the serial record."""
    # rows "short" whatever the machine's load: a task may take a minute
    monkeypatch.setattr(batch, "TASK_SECONDS", 60.0)
    folder, _, rows = pair_files
    n = 16
    many = [{**rows[k % N_ROWS], "name": f"g{k}", "seed": str(k)} for k in range(n)]
    table = _write_csv(folder / f"grouped-{chunk}.csv", many, columns=("name", "source", "target", "seed"))
    with distributed.get_task_stream(client) as stream:
        result = batch.run(table, tmp_path / "dask", scheduler=client, chunk=chunk)
    keys = _gatv_tasks(stream)
    sizes = sorted(int(k.split("-")[-3]) for k in keys)  # gatv-<command>-<first row>-<rows>-<stamp>
    assert sum(sizes) == n
    if chunk:
        assert sizes == [1, 3, 3, 3, 3, 3]
    else:  # the first 2 x threads tasks are single rows, then at most a quarter of the rows left
        assert sizes.count(1) >= 4 and max(sizes) == (n - 4) // 4 and len(keys) < n
    serial = batch.run(table, tmp_path / "serial", scheduler="serial")
    assert sorted(p.name for p in (tmp_path / "dask").glob("*.json")) == sorted(f"g{k}.json" for k in range(n))
    for a, b in zip(serial.rows, result.rows):
        assert (a.name, a.status) == (b.name, b.status)
        assert _record_without_times(json.loads(a.path.read_text())) == \
            _record_without_times(json.loads(b.path.read_text()))


def test_bad_chunk_names_the_argument(tmp_path, pair_files, capsys):
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    with pytest.raises(InputError, match="`chunk`"):
        batch.run(table, tmp_path / "o", scheduler="serial", chunk=0)
    assert not (tmp_path / "o").exists()
    assert cli.main(["batch", str(table), "--out", str(tmp_path / "o"), "--chunk", "0"]) == 2
    _one_error(capsys, "--chunk")
    assert not (tmp_path / "o").exists()


def test_local_workers_run_without_the_profiler(client):
    """The local cluster's workers skip the dashboard's sampling profiler and the 20 ms tick."""
    import dask

    def settings():
        return dask.config.get("distributed.worker.profile.enabled"), dask.config.get("distributed.admin.tick.interval")

    assert set(client.run(settings).values()) == {(False, "200ms")}
    assert dask.config.get("distributed.worker.profile.enabled") is True  # this process's config is left alone


def test_local_workers_keep_glibcs_malloc_thresholds(client):
    """Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers by default, which fixes glibc's mmap
    threshold and made each row 10-15% slower there; the local cluster's workers go without it."""
    import os

    def trim():
        return os.environ.get("MALLOC_TRIM_THRESHOLD_")

    assert set(client.run(trim).values()) == {None}
    assert set(client.run(lambda: os.environ.get("OPENBLAS_NUM_THREADS")).values()) == {"1"}


# ------------------------------------------------------------- issue 42 and 37
def test_refused_scheduler_fails_at_once(tmp_path, pair_files, capsys):
    """Nothing listens on the port: exit 2 in well under the 10 s connect timeout."""
    import socket
    import time

    with socket.socket() as sock:  # a port that was free a moment ago, closed again
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    out = tmp_path / "out"
    start = time.perf_counter()
    status = cli.main(["batch", str(table), "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{port}"])
    assert status == 2 and time.perf_counter() - start < 3.0
    _one_error(capsys, "cannot reach the Dask scheduler", "refused")
    assert not out.exists()


def test_summary_has_the_verdict_columns(tmp_path, pair_files, monkeypatch):
    """verdict_support, verdict_chance, verdict_p from info['verdict'] when a result has one."""
    from gatv.motion import RigidMotion

    folder, trials, rows = pair_files
    verdict = {"support": 20, "chance": 4.5, "n_tested": 1000.0, "p_value": 1.25e-9, "margin": 4.44,
               "passed": True}
    real_call = batch._call

    def call(task):
        source, target, opts, result, seconds = real_call(task)
        info = dict(result.info)
        info.pop("verdict", None)
        if task.row == 0:
            info["verdict"] = verdict
        fake = RigidMotion(result.rotation, result.translation, result.correspondences, info=info)
        return source, target, opts, fake, seconds

    monkeypatch.setattr(batch, "_call", call)
    table = [*({"source": str(folder / r["source"]), "target": str(folder / r["target"])} for r in rows[:2]),
             {"source": str(folder / "missing.npy"), "target": str(folder / rows[0]["target"])}]
    result = batch.run(table, tmp_path / "out", scheduler="serial")
    with open(result.summary, newline="") as fh:
        lines = list(csv.DictReader(fh))
    assert tuple(lines[0]) == batch.SUMMARY_HEADERS
    got = [(r["verdict_support"], r["verdict_chance"], r["verdict_p"]) for r in lines]
    assert got == [("20", "4.5", "1.25e-09"), ("", "", ""), ("", "", "")]
    assert [r["status"] for r in lines] == ["found", "found", "failed"]


def test_model_column_takes_the_registrys_models():
    from gatv.models import MODEL_NAMES

    tasks = batch.read_pairs([{"source": "a", "target": "b", "model": m, "name": m} for m in MODEL_NAMES])
    assert [dict(t.options)["model"] for t in tasks] == list(MODEL_NAMES)
    assert all(not t.problem for t in tasks)
    (bad,) = batch.read_pairs([{"source": "a", "target": "b", "model": "projective"}])
    assert "projective" in bad.problem and all(m in bad.problem for m in MODEL_NAMES)


# ------------------------------------------------- auto: serial until a cluster pays (issue 42)
from hypothesis import given, settings
from hypothesis import strategies as st


@given(wall=st.floats(0.001, 100.0), share=st.floats(0.3, 2.0), left=st.integers(0, 10_000),
       workers=st.integers(1, 16))
@settings(max_examples=200, deadline=None)
def test_local_cluster_starts_only_when_it_pays(wall, share, left, workers):
    cpu = wall * share
    d = batch.local_cluster_pays([(wall, cpu), (wall, cpu)], left, workers)
    import math

    expected_cluster = batch.LOCAL_START_SECONDS + batch.LOCAL_OVERHEAD * cpu * math.ceil(left / workers)
    assert d.serial_s == pytest.approx(wall * left) and d.cluster_s == pytest.approx(expected_cluster)
    if d.start:
        assert workers > 1 and left > 1
        assert d.cluster_s <= batch.LOCAL_MARGIN * d.serial_s  # expected to finish sooner, start included
        assert d.serial_s > batch.LOCAL_START_SECONDS  # never for a batch shorter than a cluster's start
    elif workers > 1 and left > 1:
        assert d.cluster_s > batch.LOCAL_MARGIN * d.serial_s


def test_short_batch_runs_serially_and_says_so(tmp_path, pair_files, capsys):
    folder, _, rows = pair_files
    table = _write_csv(folder / "pairs.csv", rows)
    assert cli.main(["batch", str(table), "--out", str(tmp_path / "o"), "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "ran on:          serial, in this process: a local cluster would not have paid" in out
    result = batch.run(table, tmp_path / "api", workers=2)
    assert result.where.startswith("serial") and result.counts()["found"] == N_ROWS


def test_auto_times_rows_on_one_numba_thread_then_runs_the_rest_on_every_thread(tmp_path, pair_files,
                                                                                 monkeypatch):
    """The rows that decide (second to MEASURED_ROWS + 1-th) run as a worker would, on one thread;
    a batch that stays here runs the others on all of this process's threads, and restores them."""
    import numba

    seen = []
    real = batch.compute

    def spy(task):
        seen.append(numba.get_num_threads())
        return real(task)

    monkeypatch.setattr(batch, "compute", spy)
    folder, _, rows = pair_files
    many = [{**rows[k % N_ROWS], "name": f"m{k}", "seed": str(k)} for k in range(7)]
    table = _write_csv(folder / "measured.csv", many, columns=("name", "source", "target", "seed"))
    before = numba.get_num_threads()
    result = batch.run(table, tmp_path / "m", workers=2)
    assert result.where.startswith("serial")
    m = batch.MEASURED_ROWS
    assert seen == [before] + [1] * m + [before] * (7 - 1 - m)
    assert numba.get_num_threads() == before


def test_auto_starts_a_local_cluster_for_long_rows_and_equals_serial(tmp_path, pair_files, monkeypatch):
    """Rows made to look long (a cluster costs nothing to start, Dask nothing per row): the rest
    runs on 2 workers."""
    monkeypatch.setattr(batch, "LOCAL_START_SECONDS", 0.0)
    monkeypatch.setattr(batch, "LOCAL_OVERHEAD", 0.1)
    folder, _, rows = pair_files
    many = [{**rows[k % N_ROWS], "name": f"a{k}", "seed": str(k)} for k in range(8)]
    table = _write_csv(folder / "auto.csv", many, columns=("name", "source", "target", "seed"))
    result = batch.run(table, tmp_path / "auto", workers=2)
    assert "then a local cluster of 2 workers" in result.where, result.where
    serial = batch.run(table, tmp_path / "serial", scheduler="serial")
    for a, b in zip(serial.rows, result.rows):
        assert _record_without_times(json.loads(a.path.read_text())) == \
            _record_without_times(json.loads(b.path.read_text()))
