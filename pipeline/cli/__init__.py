"""Command-line interface: ``python -m pipeline <command> ...`` (or the ``pipeline`` console script).

Contract: exit code 0 on success; 2 on bad input (any ``PipelineError`` or an argparse usage error), with one line
``error: <message>`` on stderr and no traceback. Other exceptions are bugs and keep their traceback.

Each command is a module ``pipeline/cli/<name>.py`` with ``add_parser(subparsers)`` (adds its sub-parser and sets
``run`` as its default ``func``) and ``run(args) -> int``; register it in ``COMMAND_MODULES``. Command modules import
the heavy library (torch, OpenCV) inside ``run`` so that ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from pipeline import __version__
from pipeline.errors import PipelineError

#: Modules under ``pipeline.cli`` that each define one command, in the order ``--help`` lists them.
COMMAND_MODULES: tuple[str, ...] = ("camera", "demo", "segment", "pose", "shape", "track", "batch")

EXIT_OK = 0
EXIT_BAD_INPUT = 2


class UsageError(PipelineError):
    """The command line itself is wrong (unknown option, missing argument)."""


class _ArgumentParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that raises ``UsageError`` instead of printing usage and exiting."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with one sub-parser per module in ``COMMAND_MODULES``."""
    parser = _ArgumentParser(
        prog="pipeline",
        description="Robot pose and soft-robot shape from one camera image by differentiable rendering.",
        epilog="Exit codes: 0 success, 2 bad input (one line 'error: ...' on stderr). "
        "Run 'pipeline <command> --help' for a command's options.",
    )
    parser.add_argument("--version", action="version", version=f"pipeline {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="log progress (-vv for debug output)")
    subparsers = parser.add_subparsers(dest="command", metavar="<command>", title="commands")
    for name in COMMAND_MODULES:
        importlib.import_module(f"pipeline.cli.{name}").add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``) and return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            raise UsageError(f"no command given; choose one of: {', '.join(COMMAND_MODULES)} (see pipeline --help)")
        logging.basicConfig(
            level=(logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)],
            format="%(levelname)s %(name)s: %(message)s",
        )
        return args.func(args)
    except SystemExit as e:  # --help and --version exit through argparse
        return e.code if isinstance(e.code, int) else EXIT_BAD_INPUT
    except PipelineError as e:
        message = " ".join(str(e).split())  # one line, whatever the message held
        print(f"error: {message}", file=sys.stderr)
        return EXIT_BAD_INPUT
