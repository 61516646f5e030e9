"""Command-line interface: ``gatv register``, ``segment``, ``instances``, ``track``, ``nonrigid``,
``catadioptric``, ``batch``, ``demo`` and ``warmup``.

Installed as the ``gatv`` console script and runnable as ``python -m gatv``.

Every command is a module of this package listed in :data:`COMMANDS`; it
defines ``add_parser(subparsers)`` and ``run(args) -> int``.  What they
share (options, output checks, the progress printer, the atomic writer of
all outputs, the error handler) lives in :mod:`gatv.cli._common`.

Exit status: 0 on success; 1 when no motion was found, or on an internal
error (one line ``gatv: error: <Type>: <message> (set GATV_DEBUG=1 for a
traceback)``); 2 on bad input or options (:class:`gatv.errors.InputError`:
an unreadable or missing file, wrong shape, NaN, too few points, a value
out of range; an :class:`OSError` while reading or writing; a usage error),
reported as one line ``gatv: error: <message>``.  No traceback unless
``GATV_DEBUG=1``.  No output file is written unless the whole command
succeeds: every output is first written to a temporary file beside its
destination and all are moved into place at the end.
"""

from __future__ import annotations

import argparse
import importlib
from types import ModuleType

from ._common import EXIT_OK, EXIT_USAGE, PROG, ArgumentParser, guarded

__all__ = ["COMMANDS", "build_parser", "command", "main"]

#: The command table: command name -> module of :mod:`gatv.cli` defining
#: ``add_parser(subparsers)`` and ``run(args)``, in the order of ``--help``.
COMMANDS = {
    "register": "register",
    "segment": "segment",
    "instances": "instances",
    "track": "track",
    "nonrigid": "nonrigid",
    "catadioptric": "catadioptric",
    "batch": "batch",
    "demo": "demo",
    "warmup": "warmup",
}


def command(name: str) -> ModuleType:
    """The module of command ``name`` (its ``add_parser`` and ``run``)."""
    return importlib.import_module(f"{__name__}.{COMMANDS[name]}")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``gatv`` command."""
    parser = ArgumentParser(
        prog=PROG,
        description=(
            "Correspondences and motions between 3D point sets with Geometric Algebra and "
            "Tensor Voting (Reyes, Medioni & Bayro, IJCV 2007)."
        ),
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=ArgumentParser)
    for name in COMMANDS:
        command(name).add_parser(sub)
    return parser


@guarded
def main(argv=None) -> int:
    """Run the ``gatv`` command; return its exit status.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 success, 1 no motion found or internal error, 2 bad input.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"{PROG} {version('gatv')}")
        except PackageNotFoundError:
            print(f"{PROG} (version unknown)")
        return EXIT_OK
    if args.command is None:
        parser.print_help()
        return EXIT_USAGE
    return command(args.command).run(args)
