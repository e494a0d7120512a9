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


# --- reading: every bad file a CrchflError naming it (issue 18) ---------------------------------


def test_read_toml_refuses_non_utf8_bytes_and_deep_nesting(tmp_path):
    from crchfl_sumo.core.config import MAX_DEPTH, nesting_depth, read_toml

    path = tmp_path / "c.toml"
    path.write_bytes(b"seed = 1\n# caf\xe9\n")
    with pytest.raises(CrchflError, match=r"c.toml: not UTF-8 text \(byte 14 is b'\\xe9'\); save the config as UTF-8"):
        read_toml(path)
    for depth in (MAX_DEPTH + 1, 5000):  # over the limit; and deeper than Python's parser recursion
        path.write_text("a = " + "[" * depth + "]" * depth + "\n")
        with pytest.raises(CrchflError, match="nest deeper than 32 levels"):
            read_toml(path)
    path.write_text("a = " + "[" * (MAX_DEPTH - 1) + "]" * (MAX_DEPTH - 1) + "\n")  # the table and 31 lists: 32
    assert nesting_depth(read_toml(path)) == MAX_DEPTH
    assert nesting_depth(1) == 0 and nesting_depth({"a": 1}) == 1 and nesting_depth({"a": [{"b": []}]}) == 4


def test_from_mapping_refuses_non_finite_floats_and_bad_seeds_for_every_field():
    from dataclasses import dataclass

    from crchfl_sumo.core.config import from_mapping

    @dataclass(frozen=True)
    class Demo:
        rate_bps: float = 1.0
        deadline_s: float = math.inf
        sizes: tuple[float, ...] = (1.0,)
        seed: int = 0
        drive_seed: int = 0

    assert from_mapping(Demo, {"deadline_s": math.inf}).deadline_s == math.inf  # inf: the default's "no limit"
    for data, message in [
        ({"rate_bps": math.nan}, "demo.rate_bps: nan is not allowed; give a finite number"),
        ({"rate_bps": math.inf}, "demo.rate_bps: inf is not allowed; give a finite number"),
        ({"deadline_s": -math.inf}, r"demo.deadline_s: -inf is not allowed; give a finite number or inf \(no limit\)"),
        ({"deadline_s": math.nan}, "demo.deadline_s: nan is not allowed"),
        ({"sizes": [1.0, math.nan]}, r"demo.sizes\[1\]: nan is not allowed"),
        ({"seed": -1}, "demo.seed: -1 is outside the seed range"),
        ({"drive_seed": 2**64}, "demo.drive_seed: 18446744073709551616 is outside the seed range"),
    ]:
        with pytest.raises(CrchflError, match=message):
            from_mapping(Demo, data, "demo")


def test_a_dataclass_s_own_errors_name_the_file_and_the_table(tmp_path):
    from crchfl_sumo.core.config import from_mapping, load_tables
    from crchfl_sumo.federation.run_config import RunConfig
    from crchfl_sumo.planning.settings import AllocationConfig

    def message(data, where):
        with pytest.raises(CrchflError) as info:
            from_mapping(RunConfig, {"dataset": "d", **data}, where)
        return str(info.value)

    where = str(tmp_path / "run.toml")
    # the table's own key, joined to the file's dotted path
    assert message({"federation": {"deadline_s": 1e308}}, where) == (
        f"{where}.federation.deadline_s: 1e+308 is out of range; give simulated seconds (or inf: no deadline) "
        "in (0, 86400]"
    )
    # a cross-key check of the table ("sumo: ...") and one of the whole file (RunConfig's own, no table prefix)
    assert message({"sumo": {"edge_site_count": 2, "edge_sites": [{"name": "a", "x_m": 0, "y_m": 0}]}}, where) == (
        f"{where}.sumo: give either edge_sites or edge_site_count, not both"
    )
    assert message({"data_mode": "online", "clock": {"kind": "constant"}}, where).startswith(f"{where}: ")
    # a table read by load_tables ("FILE: allocation"): the key follows the file once
    config = tmp_path / "plan.toml"
    config.write_text("[allocation]\nrate_window_s = 1e9\n")
    with pytest.raises(CrchflError) as info:
        load_tables(config, {"allocation": AllocationConfig})
    assert str(info.value).startswith(f"{config}: allocation.rate_window_s: 1e+09 is out of range")
    assert str(info.value).count(str(config)) == 1
