"""docs/api.md: its examples run as written, in order, in a scratch folder."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def examples() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(encoding="utf-8"), re.S)


def test_the_api_page_has_an_example_for_each_command_it_promises():
    text = "\n".join(examples())
    for name in ("run_simulate_command", "generate_dataset", "train_command", "drive_route", "run_benchmark",
                 "make_plan", "run_command"):
        assert f"{name}(" in text, name


@pytest.mark.slow
def test_the_api_examples_run_as_written(tmp_path, capsys):
    here = os.getcwd()
    os.chdir(tmp_path)
    try:
        for code in examples():
            exec(compile(code, str(DOC), "exec"), {"__name__": "api_example"})
    finally:
        os.chdir(here)
    printed = capsys.readouterr().out.splitlines()
    assert printed[5] == "449 5 1 9"  # make_plan's paper plan, as the page says
    assert (tmp_path / "out" / "run" / "summary.json").is_file()
    assert (tmp_path / "out" / "bench" / "episodes.json").is_file()
