"""docs/cli.md is the output of ``python -m pipeline.cli.docs``, and that output covers every command and option."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from pipeline.cli import COMMAND_MODULES, build_parser
from pipeline.cli.docs import cli_markdown

REPO = Path(__file__).resolve().parents[1]
CLI_MD = REPO / "docs" / "cli.md"


def test_cli_md_is_up_to_date():
    assert CLI_MD.read_text() == cli_markdown(), (
        "docs/cli.md is stale: regenerate it with 'python -m pipeline.cli.docs > docs/cli.md'"
    )


def test_every_command_and_option_is_documented():
    text = cli_markdown()
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert list(subparsers.choices) == list(COMMAND_MODULES)
    for name, sub in subparsers.choices.items():
        section = text.split(f"\n## pipeline {name}\n", 1)[1].split("\n## ", 1)[0]
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            for option in action.option_strings:
                assert f"`{option}" in section or f", {option}" in section, (name, option)


def test_a_command_added_later_appears():
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    new = subparsers.add_parser("frobnicate", help="a command from another branch", description="Frobnicate.")
    new.add_argument("--level", type=int, default=0, metavar="N", help="how much (default %(default)s)")
    text = cli_markdown(parser)
    assert "| [`frobnicate`](#pipeline-frobnicate) | a command from another branch |" in text
    assert "## pipeline frobnicate\n\nFrobnicate." in text
    assert "| `--level N` | `0` | how much (default 0) |" in text


def test_the_module_prints_the_reference():
    out = subprocess.run([sys.executable, "-m", "pipeline.cli.docs"], capture_output=True, text=True, check=True,
                         cwd=REPO).stdout
    assert out == cli_markdown()
