"""README's table of commands names every option each command's parser has, and no other."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from crchfl_sumo.cli import build_parser

README = Path(__file__).resolve().parents[1] / "README.md"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


def test_the_readme_table_names_each_commands_options():
    rows = re.findall(r"^\| `crchfl-sumo ([a-z-]+)([^`]*)` \|", README.read_text(), re.M)
    commands = _subparsers(build_parser())
    assert sorted(cmd for cmd, _ in rows) == sorted(commands)  # every command has its row, once
    for cmd, usage in rows:
        named = set(re.findall(r"--[a-z][a-z0-9-]*[a-z0-9]", usage))
        options = {o for a in commands[cmd]._actions for o in a.option_strings if o.startswith("--")} - {"--help"}
        assert named == options, (cmd, sorted(options - named), sorted(named - options))
