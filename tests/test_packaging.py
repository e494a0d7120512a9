"""The built-in scenarios ship inside the wheel, though they live at the repository's top."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import crchfl_sumo
from crchfl_sumo.core.resources import drive_routes_path, experiments_dir, scenarios_dir, street_types_path
from crchfl_sumo.core.resources import builtin_names

REPO = Path(__file__).resolve().parents[1]
BUILTIN = ("paper", "paper_linked", "scale200", "town01", "town02")


def test_the_accessor_finds_every_builtin_scenario_and_preset():
    assert set(BUILTIN) <= set(builtin_names())
    for name in BUILTIN:
        assert (scenarios_dir() / name / "scenario.toml").is_file(), name
    assert drive_routes_path().is_file() and street_types_path().is_file()
    assert {p.stem for p in experiments_dir().glob("*.toml")} >= {"crchfl", "hfl", "sfl", "reproduce_quick",
                                                                  "reproduce_full"}


@pytest.mark.slow
def test_the_wheel_holds_the_towns_presets_and_every_subpackage(tmp_path):
    pytest.importorskip("setuptools")
    # a copy of the source, so the build's own folders stay out of the checkout
    source = tmp_path / "source"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(".git", ".venv", "build", "results", "*.egg-info",
                                                                 "__pycache__"))
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path),
         str(source)],
        check=True, capture_output=True,
    )
    (wheel,) = tmp_path.glob("crchfl_sumo-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for town in ("town01", "town02"):
        assert f"crchfl_sumo/scenarios/{town}/{town}.net.xml" in names
        assert f"crchfl_sumo/scenarios/{town}/scenario.toml" in names
    assert "crchfl_sumo/scenarios/experiments/reproduce_quick.toml" in names
    assert "crchfl_sumo/scenarios/drive_routes.toml" in names
    for layer in crchfl_sumo.LAYERS:
        assert f"crchfl_sumo/{layer}/__init__.py" in names, layer
