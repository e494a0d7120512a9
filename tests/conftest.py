"""Shared fixtures: a tiny signalised grid network built by netgenerate (fast, no built-ins needed)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from crchfl_sumo.sumo.installation import sumo_binary


def _tool(name: str) -> str:
    return sumo_binary(name)


ROUTES = """<routes>
  <vType id="car" accel="2.6" decel="4.5" length="4.5" width="1.8" sigma="0.5"/>
  <route id="east" edges="A0B0 B0C0"/>
  <route id="north" edges="B0B1 B1B2"/>
  <flow id="fe" type="car" route="east" begin="0" end="120" period="6" departSpeed="max"/>
  <flow id="fn" type="car" route="north" begin="3" end="120" period="6" departSpeed="max"/>
</routes>
"""


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread():
    """The tests train tiny models: one torch thread. More only contend on a busy 2-core machine
    (measured there: 90 ms a batch on one thread, 480 to 800 ms on two)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def grid_dir(tmp_path_factory) -> Path:
    """A 3x3 grid (200 m blocks, traffic lights) with two flows, and a plain .sumocfg."""
    folder = tmp_path_factory.mktemp("grid")
    subprocess.run(
        [
            _tool("netgenerate"),
            "--grid",
            "--grid.number=3",
            "--grid.length=200",
            "--default-junction-type=traffic_light",
            "--no-turnarounds=true",
            "-o",
            str(folder / "grid.net.xml"),
        ],
        check=True,
        capture_output=True,
    )
    (folder / "routes.rou.xml").write_text(ROUTES)
    (folder / "grid.sumocfg").write_text(
        """<configuration>
  <input><net-file value="grid.net.xml"/><route-files value="routes.rou.xml"/></input>
  <time><step-length value="0.5"/></time>
</configuration>
"""
    )
    return folder
