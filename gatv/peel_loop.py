"""The one peel loop: search, accept, remove, repeat (paper, section 5).

"After the first plane was detected, we removed its tokens from the voting
space and the process was repeated until no more planes were found."  Every
pipeline that finds several motions does this: the point-set peel
(:func:`gatv.motions.peeling.peel`), the scan scenes
(:func:`gatv.motions.scans.segment_scans`), the non-rigid parts
(:func:`gatv.nonrigid.segment`) and the planes on the catadioptric sphere
(:func:`catadioptric.peeling.peel`).  They differ in how a motion is found
and judged, not in the loop, so the loop is written once here and each
pipeline plugs in its steps:

* **search** ``() -> Candidate | Stop`` proposes the best motion on what
  remains (Algorithm 1's search, on the points no kept motion explains),
  or says why there is nothing left to search (a :class:`Stop`);
* **accept** ``(candidate) -> judgement`` judges it: anything with a
  boolean ``passed`` (a :class:`Judgement`, or a
  :class:`gatv.verdict.Verdict`, the chance test of the verdict stage);
* **remove** ``(candidate, judgement) -> items`` takes the accepted
  motion's points out of what remains (its tokens leave the voting space)
  and returns what the round kept (one motion, or several: a non-rigid
  registration may split into parts);
* **reject** ``(candidate, judgement) -> Stop | None`` (optional) decides
  what a rejected candidate means: by default the loop stops there (no
  motion beats chance on what remains); a pipeline that searches a
  rejected part again, or tolerates a few wrong motions before giving up,
  records it and returns ``None`` to go on.

The loop itself stops at ``max_motions`` motions kept, at a ``deadline``,
after ``max_rounds`` rounds (a bound no pipeline reaches: each step must
make progress, and this makes a step that does not end the loop rather
than hang it), or when a step says so.  The stop reasons are the
pipelines' own sentences (``info["reason"]``), passed through unchanged.

The steps are closures over the pipeline's state; the loop only sequences
them, so a pipeline's results are what its own loop gave, seed for seed.
This module imports no pipeline.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

__all__ = ["MAX_ROUNDS", "Candidate", "Judgement", "PeelOutcome", "Round", "Stop", "peel_loop"]

#: Rounds after which the loop stops whatever the steps say.  Each round
#: runs a search, so no pipeline comes near it; it turns a step that makes
#: no progress into a stop with a reason instead of an endless loop.
MAX_ROUNDS = 10_000


@dataclass(frozen=True, eq=False)
class Candidate:
    """What the search step proposes: a motion and its support on what remains.

    Attributes
    ----------
    motion : object
        The pipeline's motion (a :class:`gatv.stages.Fit`, a rotation and
        translation, a registration result, a homography...); ``None`` when
        the search of one part found nothing and the pipeline still wants
        the round judged (and rejected) rather than the loop stopped.
    support : int
        Its support (points or pairs) on what remains.
    detail : object
        Whatever the pipeline's accept and remove steps need from the
        search (its round record, the rows searched); opaque to the loop.
    """

    motion: Any
    support: int
    detail: Any = None


@dataclass(frozen=True)
class Stop:
    """Why the loop stops.

    Attributes
    ----------
    reason : str
        The sentence the pipeline reports (``info["reason"]``).
    exhausted : bool
        True when it stopped for want of a motion to find (nothing left, no
        motion beats chance), False at a limit (``max_motions``, a time or
        work bound, the rounds, too many rejections).  The point-set peel
        searches again the points wrong motions held out only in the first
        case.
    """

    reason: str
    exhausted: bool = False


@dataclass(frozen=True, eq=False)
class Judgement:
    """The accept step's answer on one candidate.

    Attributes
    ----------
    passed : bool
        Keep it (and remove its points).
    reason : str
        Why not (a rejection's stop reason when the loop stops there), or
        the pipeline's word for the outcome (``"kept"``, ``"chance"``...).
    verdict : gatv.verdict.Verdict or None
        The verdict stage's figures, when the step computed them.
    detail : object
        Whatever the remove or reject step needs (a settled fit, the
        rejection's record); opaque to the loop.
    """

    passed: bool
    reason: str = ""
    verdict: Any = None
    detail: Any = None

    def __bool__(self) -> bool:
        return bool(self.passed)


class Judged(Protocol):
    """What an accept step may return: a :class:`Judgement` or a :class:`gatv.verdict.Verdict`."""

    @property
    def passed(self) -> bool: ...


@dataclass(frozen=True, eq=False)
class Round:
    """One round's outcome.

    Attributes
    ----------
    index : int
        0 for the first round.
    candidate : Candidate or None
        What the search proposed (``None`` when it stopped the loop).
    judgement : Judgement, Verdict or None
        The accept step's answer (``None`` when there was no candidate).
    kept : tuple
        What the remove step returned (empty for a rejected candidate).
    stop : str or None
        The stop reason when the loop stopped in this round.
    """

    index: int
    candidate: Candidate | None
    judgement: Any
    kept: tuple
    stop: str | None = None

    @property
    def motion(self):
        """The candidate's motion (``None`` without one)."""
        return None if self.candidate is None else self.candidate.motion

    @property
    def support(self) -> int:
        """The candidate's support (0 without one)."""
        return 0 if self.candidate is None else int(self.candidate.support)

    @property
    def passed(self) -> bool:
        """Whether the round kept its candidate."""
        return self.judgement is not None and bool(self.judgement.passed)

    @property
    def reason(self) -> str:
        """The stop reason, else the judgement's reason (its sentence for a verdict)."""
        if self.stop is not None:
            return self.stop
        return "" if self.judgement is None else judgement_reason(self.judgement)


@dataclass(frozen=True, eq=False)
class PeelOutcome:
    """What the loop found and why it stopped.

    Attributes
    ----------
    found : tuple
        The items the remove steps returned, in the order kept.
    reason : str
        Why it stopped (a step's sentence, or the loop's own at a limit).
    exhausted : bool
        As :attr:`Stop.exhausted`.
    rounds : tuple of Round
        Every round run, the stopping one included.
    """

    found: tuple
    reason: str
    exhausted: bool
    rounds: tuple

    @property
    def n_rounds(self) -> int:
        """Rounds run (searches started)."""
        return len(self.rounds)


def judgement_reason(judgement) -> str:
    """A judgement's reason: its ``reason`` string, or the sentence of a :class:`gatv.verdict.Verdict`."""
    reason = getattr(judgement, "reason", "")
    return str(reason() if callable(reason) else reason)


def stop_on_reject(candidate: Candidate, judgement) -> Stop:
    """The default reject step: a rejected candidate ends the loop (no motion beats chance on what remains)."""
    return Stop(judgement_reason(judgement) or "the best motion on what remains was rejected", exhausted=True)


def peel_loop(search: Callable[[], Candidate | Stop], accept: Callable[[Candidate], Judged],
              remove: Callable[[Candidate, Any], Sequence], *, max_motions: int | None = None,
              reject: Callable[[Candidate, Any], Stop | None] | None = None,
              report: Callable[[Round], None] | None = None, deadline: float | None = None,
              max_rounds: int = MAX_ROUNDS, full: str = "max_motions reached",
              late: str = "the time limit ran out before the next round",
              clock: Callable[[], float] = time.perf_counter) -> PeelOutcome:
    """Search, accept, remove, until a step or a limit stops it (the module docstring).

    Each round first checks the limits, in this order: ``max_motions``
    items kept (reason ``full``), the ``deadline`` passed (on ``clock``;
    reason ``late``), ``max_rounds`` rounds
    run.  Then it calls ``search``; a :class:`Stop` ends the loop.  Else
    ``accept`` judges the candidate: a passed one goes to ``remove``,
    whose items are kept; a rejected one to ``reject`` (default
    :func:`stop_on_reject`), which ends the loop with a :class:`Stop` or
    lets it go on with ``None``.  ``report(round)`` sees every round.

    Parameters
    ----------
    search, accept, remove, reject : callable
        The pipeline's steps.
    max_motions : int, optional
        Items to keep at most (0 stops before the first search).
    report : callable, optional
        Called with each :class:`Round` once it has run.
    deadline : float, optional
        :func:`time.perf_counter` time after which no round starts.
    max_rounds : int, default: :data:`MAX_ROUNDS`
    full, late : str
        The reasons given at ``max_motions`` and at the ``deadline``.
    clock : callable, default: :func:`time.perf_counter`
        The clock ``deadline`` is read on.

    Returns
    -------
    PeelOutcome
    """
    reject = stop_on_reject if reject is None else reject
    found: list = []
    rounds: list[Round] = []

    def finish(stop: Stop, rnd: Round | None = None) -> PeelOutcome:
        if rnd is not None:
            rounds.append(rnd)
            if report is not None:
                report(rnd)
        return PeelOutcome(tuple(found), stop.reason, bool(stop.exhausted), tuple(rounds))

    while True:
        if max_motions is not None and len(found) >= max_motions:
            return finish(Stop(full))
        if deadline is not None and clock() >= deadline:
            return finish(Stop(late))
        if len(rounds) >= max_rounds:
            return finish(Stop(f"{max_rounds} rounds run without the steps stopping"))
        index = len(rounds)
        proposal = search()
        if isinstance(proposal, Stop):
            return finish(proposal, Round(index, None, None, (), proposal.reason))
        judgement = accept(proposal)
        if judgement.passed:
            kept = tuple(remove(proposal, judgement))
            found.extend(kept)
            rnd = Round(index, proposal, judgement, kept)
        else:
            stop = reject(proposal, judgement)
            if stop is not None:
                return finish(stop, Round(index, proposal, judgement, (), stop.reason))
            rnd = Round(index, proposal, judgement, ())
        rounds.append(rnd)
        if report is not None:
            report(rnd)
