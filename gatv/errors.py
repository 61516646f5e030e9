"""Exceptions of gatv.

:class:`InputError` marks bad input or options: every validator of gatv
raises it, with a message naming the argument and the fix.  It subclasses
:class:`ValueError`, so ``except ValueError`` keeps working; the command
line maps it (and unreadable files) to exit status 2, and any other
exception to exit status 1 (an internal error).
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad input or options; the message names the argument and the fix."""
