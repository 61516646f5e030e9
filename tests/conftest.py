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
