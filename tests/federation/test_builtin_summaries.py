"""The built-in run configs (crchfl, hfl, sfl) give the summaries they gave when this file was written, and
crchfl and hfl with asynchronous edges those they gave before the scheme steps became objects: a guard
for refactors that must keep every result bit for bit. Each runs on the tiny test data set, on the
constant clock, with the arithmetic trainer (SumTrainer): bytes, rounds, simulated times, the
optimizer's plan and the metrics of the loop are all compared. Keys added to summary.json since are not.

After an intended change of results, write the file anew: `python tests/federation/test_builtin_summaries.py`.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from crchfl_sumo.core.config import from_mapping, read_toml
from crchfl_sumo.federation.run import run_federation_dir
from crchfl_sumo.federation.run_config import RunConfig, builtin_experiments
from crchfl_sumo.federation.run_data import read_inputs

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers import PAPER_VEHICLES, SumTrainer, write_dataset  # noqa: E402

GOLDEN = Path(__file__).resolve().parents[1] / "fixtures" / "builtin_summaries.json"
ASYNC_GOLDEN = Path(__file__).resolve().parents[1] / "fixtures" / "async_summaries.json"
# Asynchronous edges, with vehicles of two compute tiers so that updates arrive stale.
ASYNC = {"clock": {"kind": "constant", "compute_profile": "tiers", "compute_tiers": [1.0, 3.0]},
         "federation": {"aggregation": "async", "async_buffer": 2}}


def summary_of(name: str, tmp: Path, changes: dict | None = None) -> dict:
    """summary.json of the built-in config ``name`` run on the tiny data set, constant clock, SumTrainer;
    ``changes``: {table: keys} set over the config's (ASYNC)."""
    mapping = read_toml(builtin_experiments()[name])
    mapping["dataset"] = str(write_dataset(tmp / "data", PAPER_VEHICLES))
    mapping["clock"] = {"kind": "constant"}
    mapping.setdefault("model", {}).update(image_height=48, image_width=64)
    for table, keys in (changes or {}).items():
        mapping[table] = {**mapping.get(table, {}), **keys}
    config = from_mapping(RunConfig, mapping)
    return json.loads(json.dumps(run_federation_dir(config, read_inputs(config), tmp / name, trainer=SumTrainer())))


@pytest.mark.parametrize("name", ["crchfl", "hfl", "sfl"])
def test_a_builtin_config_gives_the_summary_it_gave(name, tmp_path):
    golden = json.loads(GOLDEN.read_text())[name]
    summary = summary_of(name, tmp_path)
    assert {key: summary.get(key) for key in golden} == golden


@pytest.mark.parametrize("name", ["crchfl", "hfl"])
def test_async_edges_give_the_summary_they_gave(name, tmp_path):
    golden = json.loads(ASYNC_GOLDEN.read_text())[name]
    summary = summary_of(name, tmp_path, ASYNC)
    assert {key: summary.get(key) for key in golden} == golden


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        summaries = {name: summary_of(name, Path(tmp) / name) for name in sorted(builtin_experiments())}
        GOLDEN.write_text(json.dumps(summaries, indent=1, sort_keys=True) + "\n")
        summaries = {name: summary_of(name, Path(tmp) / f"async-{name}", ASYNC) for name in ("crchfl", "hfl")}
        ASYNC_GOLDEN.write_text(json.dumps(summaries, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")
