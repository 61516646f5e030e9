"""Can the tests fail?  One-line bugs in a copy of the core, and which tests catch each.

Each mutation replaces one line of ``gatv/`` or ``catadioptric/`` (eq. 41,
its consistency check, the cheapest-first one-to-one selection, the chance
level, and the lines behind tests that once could not fail) in a temporary
copy of the packages; the named test files of this checkout then run against
that copy (``PYTHONPATH`` and the working directory point at it, checked by
importing ``gatv`` there first).  A mutation no test catches is a test to
write.  A mutation whose line is no longer in the source (the code moved on)
is reported as such, not as caught.

The copy keeps the files' modification times, so numba's on-disk cache of
the unchanged modules is reused; only the mutated module's kernels compile.

Usage::

    python benchmarks/mutations.py [--only NAME,NAME] [--tests tests/test_eq41.py,...] [--list]

Prints a markdown table (mutation, file, tests run, failing tests) and
exits non-zero when some applicable mutation survived.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    path: str  # relative to the repository root
    old: str  # the exact text replaced (its first occurrence)
    new: str
    tests: tuple[str, ...]
    what: str
    select: str = ""  # a pytest -k expression, if only some tests of the files apply


EQ41 = ("tests/test_eq41.py",)
MUTATIONS = (
    Mutation("eq41-length-no-abs", "gatv/ga.py",
             'return np.abs(np.einsum("...i,...i->...", V, Vs)) / np.where(nvs > 0, nvs, 1.0)',
             'return np.einsum("...i,...i->...", V, Vs) / np.where(nvs > 0, nvs, 1.0)', EQ41,
             "ga.eq41_length_residual without abs()"),
    Mutation("eq41-length-over-V", "gatv/ga.py", "nvs = np.linalg.norm(Vs, axis=-1)",
             "nvs = np.linalg.norm(V, axis=-1)", EQ41, "ga.eq41_length_residual divided by |V|, not |Vs|"),
    Mutation("eq41-residual-over-V", "gatv/ga.py", "den = np.linalg.norm(Vs, axis=-1)",
             "den = np.linalg.norm(V, axis=-1)", EQ41, "ga.eq41_residual('length') divided by |V|, not |Vs|"),
    Mutation("eq41-swapped", "gatv/ga.py", "return np.cross(V, np.cross(A, Vs))",
             "return np.cross(Vs, np.cross(A, V))", EQ41, "ga.eq41 as Vs × (A × V)"),
    Mutation("eq41-axis-unnormalised", "gatv/ga.py", "A = A / np.linalg.norm(A, axis=-1, keepdims=True)",
             "A = A", EQ41, "ga.eq41 without normalising the axis"),
    Mutation("consistent-no-double-match", "gatv/models/rigid/__init__.py",
             "same = (pairs[:, 0] == pairs[ref, 0]) ^ (pairs[:, 1] == pairs[ref, 1])",
             "same = np.zeros(len(pairs), bool)", EQ41,
             "eq41_consistent keeps tokens that share the reference's point"),
    Mutation("consistent-length-half-only", "gatv/models/rigid/__init__.py",
             "return np.union1d(cons[r <= tau], [ref])", "return cons", EQ41,
             "eq41_consistent skips the full constraint"),
    Mutation("consistent-widest-normal", "gatv/models/rigid/__init__.py",
             "n = np.linalg.svd(c, full_matrices=False)[2][-1]", "n = np.linalg.svd(c, full_matrices=False)[2][0]",
             EQ41, "plane_normal's first fit takes the widest direction"),
    Mutation("one-to-one-dearest-first", "gatv/candidates.py",
             'order = np.argsort(np.asarray(cost, dtype=np.float64), kind="stable")',
             'order = np.argsort(-np.asarray(cost, dtype=np.float64), kind="stable")', EQ41,
             "one_to_one takes the dearest pair first"),
    Mutation("one-to-one-unstable", "gatv/candidates.py",
             'order = np.argsort(np.asarray(cost, dtype=np.float64), kind="stable")',
             "order = np.argsort(np.asarray(cost, dtype=np.float64))", EQ41,
             "one_to_one's ties not to the earlier row"),
    Mutation("one-to-one-targets-reused", "gatv/candidates.py", "if used_i[i] or used_j[j]:", "if used_i[i]:",
             EQ41, "one_to_one lets a target be used twice"),
    Mutation("chance-not-family-wise", "gatv/stats.py",
             "return int(poisson.isf(alpha / max(n_tests, 1.0), n_source * p))",
             "return int(poisson.isf(alpha, n_source * p))", ("tests/test_verdict.py",),
             "the chance level ignores n_tests (no family-wise correction)"),
    Mutation("motion-parts-no-continuity", "gatv/nonrigid/multiscale.py",
             "ok = np.linalg.norm(d[a] - d[b], axis=1) <= strain * np.linalg.norm(xs[a] - xs[b], axis=1) + gate",
             "ok = np.ones(a.shape, bool)", ("tests/test_nonrigid_scale.py",),
             "motion_parts joins neighbours whatever their displacements", select="motion_parts"),
    Mutation("motion-parts-smallest-first", "gatv/nonrigid/multiscale.py",
             "rank[np.argsort(-sizes, kind=\"stable\")] = np.arange(sizes.size)",
             "rank[np.argsort(sizes, kind=\"stable\")] = np.arange(sizes.size)", ("tests/test_nonrigid_scale.py",),
             "motion_parts labels the smallest part 0", select="motion_parts"),
    Mutation("voting-support-miscounted", "catadioptric/voting.py",
             'info["voting_support"] = int(sel.shape[0])', 'info["voting_support"] = int(sel.shape[0]) + 1',
             ("tests/test_catadioptric_motions.py",), "strategy='voting' reports one pair more than it kept",
             select="voting"),
)


def _copy_package(dest: Path) -> None:
    for package in ("gatv", "catadioptric"):
        shutil.copytree(ROOT / package, dest / package, copy_function=shutil.copy2,
                        ignore=shutil.ignore_patterns("*.pyc"))


def run_mutation(m: Mutation, tests=None, timeout=900) -> dict:
    """Apply ``m`` in a fresh copy of ``gatv/`` and run its tests there; returns the outcome."""
    source = (ROOT / m.path).read_text()
    args_tests = bool(tests)
    tests = tuple(tests or m.tests)
    if m.old not in source:
        return {"name": m.name, "status": "not applicable (line not found)", "failed": [], "tests": tests,
                "seconds": 0.0}
    with tempfile.TemporaryDirectory(prefix="gatv-mutant-") as tmp:
        tmp = Path(tmp)
        _copy_package(tmp)
        (tmp / m.path).write_text(source.replace(m.old, m.new, 1))
        env = dict(os.environ, PYTHONPATH=str(tmp), PYTHONDONTWRITEBYTECODE="1")
        where = subprocess.run([sys.executable, "-c", f"import {m.path.split('/')[0]} as p; print(p.__file__)"],
                               cwd=tmp, env=env,
                               capture_output=True, text=True, check=False).stdout.strip()
        if not where.startswith(str(tmp)):
            return {"name": m.name, "status": f"copy not imported ({where})", "failed": [], "tests": tests,
                    "seconds": 0.0}
        t0 = time.perf_counter()
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-c", str(ROOT / "pyproject.toml"),
               "--rootdir", str(ROOT), "-rfX", "--no-header",
               *(["-k", m.select] if m.select and not args_tests else []),
               *[str(ROOT / t) for t in tests]]
        try:
            proc = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=timeout,
                                  check=False)
            out = proc.stdout + proc.stderr
            rc = proc.returncode
        except subprocess.TimeoutExpired:
            out, rc = "", -1
        seconds = time.perf_counter() - t0
    failed = sorted({re.sub(r"\[.*$", "", line.split()[1]).split("::")[-1]
                     for line in out.splitlines() if line.startswith(("FAILED", "XPASS"))})
    if rc == -1:
        status = "timed out"
    elif rc == 0:
        status = "SURVIVED"
    elif failed:
        status = "caught"
    else:
        status = f"error (rc {rc}): " + " ".join(out.split()[-12:])
    return {"name": m.name, "status": status, "failed": failed, "tests": tests, "seconds": seconds}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="comma-separated mutation names")
    parser.add_argument("--tests", default="", help="comma-separated test files, instead of each mutation's own")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    args = parser.parse_args(argv)
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only.split(",")]
    if args.list:
        for m in chosen:
            print(f"{m.name}: {m.what} ({m.path}; tests {', '.join(m.tests)})")
        return 0
    tests = [t for t in args.tests.split(",") if t] or None
    rows = []
    for m in chosen:
        r = run_mutation(m, tests)
        rows.append(r)
        print(f"  {m.name}: {r['status']} in {r['seconds']:.0f} s; {', '.join(r['failed']) or '-'}",
              file=sys.stderr, flush=True)
    print("| mutation | what | file | tests run | outcome | failing tests |")
    print("|---|---|---|---|---|---|")
    for m, r in zip(chosen, rows):
        print(f"| {m.name} | {m.what} | {m.path} | {', '.join(Path(t).name for t in r['tests'])} | {r['status']} | "
              f"{', '.join(r['failed']) or '–'} |")
    return 1 if any(r["status"] == "SURVIVED" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
