"""config.toml_text: configs written back as TOML (by tomli-w) read back equal."""

import math
import sys

import numpy as np
import pytest

from crchfl_sumo.core.config import toml_text
from crchfl_sumo.core.errors import CrchflError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_toml_text_reads_back_equal():
    mapping = {
        "scenario": "paper",
        "dataset": 'data "quoted"',
        "flag": True,
        "ratio": 0.1,
        "deadline_s": math.inf,
        "counts": [2, 3],
        "names": ["a b", 'quote"d'],
        "federation": {"scheme": "crchfl", "seed": 3, "use_plan": False, "inner": {"x": 1}},
        "only_tables": {"a": {"b": 2}},
        "list_of_tables": [{"town": "t1", "n": [1, 2]}],
        "sumo": {"scale": 0.5, "edge_sites": [{"name": "a", "x_m": 1.0, "y_m": 2.5}]},
        "odd key": 1,
    }
    assert tomllib.loads(toml_text(mapping)) == mapping


def test_numpy_scalars_and_tuples_are_written_as_plain_values():
    text = toml_text({"a": np.float64(0.25), "b": np.int64(7), "c": np.bool_(True), "d": (1, -math.inf)})
    back = tomllib.loads(text)
    assert back == {"a": 0.25, "b": 7, "c": True, "d": [1, -math.inf]}
    assert type(back["b"]) is int and type(back["c"]) is bool
    assert math.isnan(tomllib.loads(toml_text({"x": np.float32("nan")}))["x"])
    with pytest.raises(CrchflError, match="cannot write"):
        toml_text({"x": object()})
