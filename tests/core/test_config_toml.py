"""config.toml_text / toml_value: configs written back as TOML read back equal."""

import math
import sys

import numpy as np
import pytest

from crchfl_sumo.core.config import toml_text, toml_value
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


def test_toml_value_by_hand():
    assert toml_value(np.float64(0.25)) == "0.25" and toml_value(np.int64(7)) == "7"
    assert toml_value(np.bool_(True)) == "true" and toml_value(-math.inf) == "-inf" and toml_value(math.nan) == "nan"
    assert toml_value([1, "x", {"k": 2}]) == '[1, "x", { k = 2 }]'
    with pytest.raises(CrchflError, match="cannot write"):
        toml_value(object())
