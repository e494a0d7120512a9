"""Fixtures shared by the driving tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers import netconvert


@pytest.fixture(scope="module")
def ladder(tmp_path_factory) -> Path:
    """Two parallel 200 m roads joined at both ends and in the middle (priority junctions, no signals):

        D ---- E ---- F        y = 100
        |      |      |
        A ---- B ---- C        y = 0
    """
    folder = tmp_path_factory.mktemp("ladder")
    nodes = {"A": (0, 0), "B": (100, 0), "C": (200, 0), "D": (0, 100), "E": (100, 100), "F": (200, 100)}
    (folder / "l.nod.xml").write_text(
        "<nodes>" + "".join(f'<node id="{n}" x="{x}" y="{y}" type="priority"/>' for n, (x, y) in nodes.items())
        + "</nodes>"
    )
    roads = ("AB", "BC", "DE", "EF", "AD", "BE", "CF")
    (folder / "l.edg.xml").write_text(
        "<edges>"
        + "".join(
            f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="1" speed="13.89" width="3.5"/>'
            for r in roads for a, b in (r, r[::-1])
        )
        + "</edges>"
    )
    netconvert(folder / "l.nod.xml", folder / "l.edg.xml", folder / "ladder.net.xml")
    (folder / "flow.rou.xml").write_text(
        '<routes><flow id="f" begin="0" end="100" period="5" departSpeed="max"><route edges="AB BC"/></flow></routes>'
    )
    (folder / "ladder.sumocfg").write_text(
        '<configuration><input><net-file value="ladder.net.xml"/><route-files value="flow.rou.xml"/></input>'
        '<time><step-length value="0.25"/></time></configuration>'
    )
    return folder

