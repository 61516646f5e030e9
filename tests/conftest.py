"""Test-suite settings.

Under CI (``CI`` set in the environment) hypothesis runs derandomized: the
same examples on every run, so a pass or a failure is reproducible.  Local
runs keep exploring new examples.
"""

from __future__ import annotations

import os

from hypothesis import settings

settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")
