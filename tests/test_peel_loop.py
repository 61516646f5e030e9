"""The one peel loop (gatv.peel_loop): its stops, its removals and its bounds, on a toy pool.

The pool is a list of groups (a group's size is its support); the search
proposes the largest group left, the accept step keeps it when it reaches a
threshold, the remove step takes it out.  The pipelines' own tests check
that their results did not change.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gatv.peel_loop import MAX_ROUNDS, Candidate, Judgement, PeelOutcome, Round, Stop, peel_loop
from gatv.verdict import chance_verdict

EMPTY = "nothing left to search"

sizes = st.lists(st.integers(0, 50), max_size=12)


class Pool:
    """Groups of points; the steps of a peel over them, counting their calls."""

    def __init__(self, groups, threshold):
        self.left = {k: n for k, n in enumerate(groups)}
        self.threshold = threshold
        self.searches = self.removed = 0
        self.taken: list[int] = []

    def search(self):
        self.searches += 1
        if not self.left:
            return Stop(EMPTY, exhausted=True)
        k = max(self.left, key=lambda g: (self.left[g], -g))
        return Candidate(k, self.left[k])

    def accept(self, c: Candidate) -> Judgement:
        ok = c.support >= self.threshold
        return Judgement(ok, "kept" if ok else f"{c.support} below {self.threshold}")

    def remove(self, c: Candidate, j: Judgement):
        assert j.passed and c.motion in self.left
        del self.left[c.motion]
        self.taken.append(c.motion)
        return (c.motion,)

    def set_aside(self, c: Candidate, j: Judgement):
        del self.left[c.motion]
        return None


def _check_rounds(out: PeelOutcome):
    assert [r.index for r in out.rounds] == list(range(out.n_rounds))
    assert tuple(x for r in out.rounds for x in r.kept) == out.found
    assert all(r.stop is None for r in out.rounds[:-1])
    for r in out.rounds:
        if not r.passed:
            assert r.kept == ()


@settings(max_examples=200, deadline=None)
@given(groups=sizes, threshold=st.integers(1, 40), max_motions=st.one_of(st.none(), st.integers(0, 12)))
def test_it_keeps_the_candidates_that_pass_in_order_until_the_first_rejection(groups, threshold, max_motions):
    pool = Pool(groups, threshold)
    out = peel_loop(pool.search, pool.accept, pool.remove, max_motions=max_motions)
    _check_rounds(out)
    # exactly the groups accepted were removed, once each, in the order kept
    assert list(out.found) == pool.taken
    assert len(set(out.found)) == len(out.found)
    assert all(groups[k] >= threshold for k in out.found)
    assert not set(out.found) & set(pool.left)
    # what a loop of its own would have kept: the largest groups while they reach the threshold
    order = sorted(range(len(groups)), key=lambda g: (-groups[g], g))
    passing = [g for g in order if groups[g] >= threshold]
    cap = len(passing) if max_motions is None else min(max_motions, len(passing))
    assert list(out.found) == passing[:cap]
    if max_motions is not None and len(out.found) == max_motions:
        assert out.reason == "max_motions reached" and not out.exhausted
        assert out.n_rounds == max_motions  # no search after the last one kept
    elif len(passing) == len(groups):
        assert out.reason == EMPTY and out.exhausted  # the search's reason, passed through
        assert out.rounds[-1].candidate is None
    else:  # the first rejected candidate stops it, with the judgement's reason
        rejected = order[len(passing)]
        assert out.reason == f"{groups[rejected]} below {threshold}" and out.exhausted
        assert out.rounds[-1].motion == rejected and not out.rounds[-1].passed
        assert rejected in pool.left
    assert pool.searches == out.n_rounds


@settings(max_examples=100, deadline=None)
@given(groups=sizes, threshold=st.integers(1, 40))
def test_a_reject_step_that_goes_on_keeps_every_group_that_passes(groups, threshold):
    pool = Pool(groups, threshold)
    out = peel_loop(pool.search, pool.accept, pool.remove, reject=pool.set_aside)
    _check_rounds(out)
    assert sorted(out.found) == sorted(k for k, n in enumerate(groups) if n >= threshold)
    assert out.reason == EMPTY and not pool.left
    assert out.n_rounds == len(groups) + 1  # one round a group, one that finds the pool empty


@settings(max_examples=100, deadline=None)
@given(n_rejected=st.integers(0, 6), limit=st.integers(1, 5), exhausted=st.booleans())
def test_the_reject_steps_stop_and_its_reason_are_passed_through(n_rejected, limit, exhausted):
    seen = []

    def reject(c, j):
        seen.append(c.motion)
        return Stop(f"{len(seen)} rejected", exhausted) if len(seen) >= limit else None

    pool = Pool([1] * n_rejected, threshold=2)

    def set_aside_then_reject(c, j):
        pool.set_aside(c, j)
        return reject(c, j)

    out = peel_loop(pool.search, pool.accept, pool.remove, reject=set_aside_then_reject)
    assert out.found == ()
    if n_rejected >= limit:
        assert out.reason == f"{limit} rejected" and out.exhausted == exhausted and out.n_rounds == limit
    else:
        assert out.reason == EMPTY and out.n_rounds == n_rejected + 1


@settings(max_examples=50, deadline=None)
@given(max_rounds=st.integers(0, 300), keep=st.booleans())
def test_steps_that_make_no_progress_stop_at_max_rounds(max_rounds, keep):
    # a search that always proposes the same thing, whether kept (and removing nothing) or set aside
    calls = itertools.count()
    out = peel_loop(lambda: (next(calls), Candidate("same", 5))[1], lambda c: Judgement(keep),
                    lambda c, j: (), reject=lambda c, j: None, max_rounds=max_rounds)
    assert out.n_rounds == max_rounds == next(calls)
    assert out.reason == f"{max_rounds} rounds run without the steps stopping" and not out.exhausted


def test_the_default_round_bound_is_finite():
    out = peel_loop(lambda: Candidate(None, 0), lambda c: Judgement(False), lambda c, j: (),
                    reject=lambda c, j: None)
    assert out.n_rounds == MAX_ROUNDS


@settings(max_examples=100, deadline=None)
@given(groups=st.lists(st.integers(5, 50), max_size=10), expires=st.integers(0, 12))
def test_a_deadline_stops_it_before_the_next_round_with_a_reason(groups, expires):
    # a clock that ticks once a round: the deadline passes before round `expires`
    ticks = itertools.count()
    pool = Pool(groups, threshold=1)
    out = peel_loop(pool.search, pool.accept, pool.remove, deadline=expires, clock=lambda: next(ticks),
                    late="out of time")
    if expires <= len(groups):
        assert out.reason == "out of time" and not out.exhausted
        assert out.n_rounds == expires == len(out.found)
    else:
        assert out.reason == EMPTY and len(out.found) == len(groups)


def test_a_deadline_already_passed_runs_no_search():
    pool = Pool([10, 20], threshold=1)
    out = peel_loop(pool.search, pool.accept, pool.remove, deadline=-math.inf)
    assert out.n_rounds == 0 and pool.searches == 0 and out.found == ()
    assert out.reason == "the time limit ran out before the next round"


def test_max_motions_zero_runs_no_search_and_full_names_the_reason():
    pool = Pool([10, 20], threshold=1)
    out = peel_loop(pool.search, pool.accept, pool.remove, max_motions=0, full="reached max_motions=0")
    assert out.n_rounds == 0 and pool.searches == 0 and out.reason == "reached max_motions=0"


def test_a_remove_step_may_keep_several_items_a_round():
    # a non-rigid registration that splits into parts: one round, two motions
    done = []

    def search():
        return Stop(EMPTY, True) if done else Candidate("both", 2)

    def remove(c, j):
        done.append(c)
        return ("part a", "part b")

    out = peel_loop(search, lambda c: Judgement(True), remove, max_motions=3)
    assert out.found == ("part a", "part b") and out.n_rounds == 2 and out.reason == EMPTY


@pytest.mark.parametrize("support", [3, 30])
def test_a_verdict_is_a_judgement(support):
    # the verdict stage's Verdict judges a candidate as it is; a failed one's sentence is the reason
    verdict = chance_verdict(support, 10, 4, method="poisson")
    out = peel_loop(lambda: Candidate("m", support), lambda c: verdict, lambda c, j: (c.motion,), max_motions=1)
    if support >= 10:
        assert out.found == ("m",) and out.reason == "max_motions reached"
    else:
        assert out.found == () and out.reason == verdict.reason() and out.exhausted
        assert out.rounds[-1].judgement is verdict


def test_report_sees_every_round():
    pool = Pool([30, 20, 3], threshold=10)
    seen: list[Round] = []
    out = peel_loop(pool.search, pool.accept, pool.remove, report=seen.append)
    assert tuple(seen) == out.rounds and [r.passed for r in seen] == [True, True, False]
    assert [r.support for r in seen] == [30, 20, 3]
    assert seen[-1].reason == out.reason == "3 below 10"
