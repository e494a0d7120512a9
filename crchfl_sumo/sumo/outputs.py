"""SUMO's own output files beside a command's results (`--sumo-output fcd,tripinfo,summary`).

Each asked-for output is OUT/sumo-NAME.xml, in SUMO's own format (sumolib.xml.parse reads it). SUMO
writes it under a temporary name, which becomes the final one once SUMO has closed the file: a
file of that name is always complete.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator, Mapping, Sequence

from crchfl_sumo.core.errors import CrchflError

SUMO_OUTPUTS = {"fcd": "--fcd-output", "tripinfo": "--tripinfo-output", "summary": "--summary-output"}


def sumo_output_files(names: Sequence[str], out_dir: Path) -> dict[str, Path]:
    """name -> the file each asked-for SUMO output ends in; an unknown name is refused with the known ones."""
    unknown = sorted(set(names) - set(SUMO_OUTPUTS))
    if unknown:
        raise CrchflError(f"--sumo-output: {', '.join(unknown)} unknown; choose from {', '.join(SUMO_OUTPUTS)}")
    return {name: Path(out_dir) / f"sumo-{name}.xml" for name in dict.fromkeys(names)}


@contextlib.contextmanager
def sumo_output_options(files: Mapping[str, Path] | None) -> Iterator[tuple[str, ...]]:
    """The SUMO options that write ``files`` (sumo_output_files) under temporary names; after a simulation
    closed inside the block, each is renamed to its final name."""
    files = dict(files or {})
    partial = {name: path.with_name(f".{path.name}.partial") for name, path in files.items()}
    for path in files.values():
        path.parent.mkdir(parents=True, exist_ok=True)
    yield tuple(f"{SUMO_OUTPUTS[name]}={path}" for name, path in partial.items())
    for name, path in files.items():  # SUMO closed them with the simulation: complete now
        os.replace(partial[name], path)
