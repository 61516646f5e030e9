"""Input checks of gatv's public calls, for the packages and models built on it.

Every public gatv call checks its arguments with these before any numba
code runs, and each check takes the argument's *name*, so that an error
(:class:`gatv.InputError`) says which argument is wrong and how to fix it.
A package built on gatv (``catadioptric``) or a new motion model behind
:mod:`gatv.models` uses the same checks, so its errors read the same.
"""

from __future__ import annotations

from ._validation import (
    DEFAULT_MEMORY_BUDGET,
    as_points,
    as_rng,
    as_vectors,
    check_finite_array,
    check_fraction,
    check_int,
    check_memory,
    check_positive,
    check_progress,
    coordinates,
    file_hint,
    frozen_array,
    memory_budget_limit,
    seed_int,
)

__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "as_points",
    "as_rng",
    "as_vectors",
    "check_finite_array",
    "check_fraction",
    "check_int",
    "check_memory",
    "check_positive",
    "check_progress",
    "coordinates",
    "file_hint",
    "frozen_array",
    "memory_budget_limit",
    "seed_int",
]
