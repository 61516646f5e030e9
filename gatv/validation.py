"""Input checks of gatv's public calls, for the packages and models built on it.

Every public gatv call checks its arguments with these before any numba
code runs, and each check takes the argument's *name*, so that an error
(:class:`gatv.InputError`) says which argument is wrong and how to fix it.
A package built on gatv (``catadioptric``) or a new motion model behind
:mod:`gatv.models` uses the same checks, so its errors read the same.
"""

from __future__ import annotations

from ._validation import *  # noqa: F403  (the checks of every public call, named in its __all__)
from ._validation import __all__ as _CHECKS
from ._validation import file_hint

__all__ = [*_CHECKS, "file_hint"]
