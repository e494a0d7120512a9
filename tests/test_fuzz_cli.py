"""A seeded fuzz of the command line (issue 18, part A): every bad input is exit 2 with a message, never a traceback.

Three families of bad input, all run in-process through ``cli.main``:

* mutated configs: every numeric leaf of the presets under scenarios/experiments/
  and every numeric key of the run config schema set to NaN, inf, negative, zero,
  huge, a string, a bool, a list or a table; unknown keys; non-UTF-8 bytes; deep
  nesting;
* every numeric command-line argument of every subcommand given NaN, inf, huge,
  negative, zero, 2**64, text and the like;
* unusable output folders: a file, a folder inside a file, a read-only folder, a
  folder holding another command's results or this command's with other settings.

A case passes when ``main`` returns 2 with one ``crchfl-sumo: error:`` line naming the
key or argument at fault, or, for a value that may well be valid (0 or -1 of a setting
whose range the fuzz cannot know), ends at the case's sentinel instead: an input made to
fail cheaply right after the checks (a missing data set, an --out that is a file), so
that no case starts real work. Anything escaping ``main`` fails the test.

Absurd magnitudes (1e308, -1e308, 2**63 - 1) are never valid: every setting has a bound
(issue 18). Besides the seeded mutations, every numeric key of every preset and schema
is given each of them once (``_huge_cases``), and no key is let through.
"""

from __future__ import annotations

import dataclasses
import math
import os
import random
import traceback
import typing
from pathlib import Path

import tomli_w

from crchfl_sumo.cli import build_parser, main
from crchfl_sumo.core.config import read_toml
from crchfl_sumo.core.resources import experiments_dir
from crchfl_sumo.federation.run_config import RunConfig
from crchfl_sumo.studies.reproduce_plan import ReproduceConfig

SEED = 18
REFUSED = ("nan", "-inf", "text", "bool", "list", "table", "1e308", "-1e308", "2**63-1")  # never a valid number
MAYBE = ("-1", "0")  # valid for some settings: the key or the sentinel
HUGE = ("1e308", "-1e308", "2**63-1")
# Presets mutated at every key of their schema too, not only at those they set (the reproduce
# schema brings the drives' [drive] table and the data set's [generate.expert]).
SCHEMAS = {"crchfl": RunConfig, "reproduce_quick": ReproduceConfig}
VALUES = {
    "nan": math.nan, "inf": math.inf, "-inf": -math.inf, "-1": -1, "0": 0, "1e308": 1e308, "-1e308": -1e308,
    "2**63-1": 2**63 - 1, "text": "text", "bool": True, "list": [1.0], "table": {"x": 1},
}


class Case(typing.NamedTuple):
    argv: list[str]
    names: tuple[str, ...]  # one of these must be in the message
    sentinels: tuple[str, ...] = ()  # or one of these (the value was valid)


def _run_case(case: Case, capsys) -> str:
    try:
        code = main(case.argv)
    except BaseException as exc:  # a traceback (SystemExit included: argument errors are one line, exit 2)
        where = traceback.extract_tb(exc.__traceback__)[-1]
        capsys.readouterr()
        return f"{case.argv}: {type(exc).__name__} at {Path(where.filename).name}:{where.lineno}: {str(exc)[:200]}"
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    problem = None
    if code != 2:
        problem = f"exit {code}"
    elif len(lines) != 1 or not lines[0].startswith("crchfl-sumo: error: "):
        problem = "not one error line"
    elif not any(n in err for n in case.names + case.sentinels):
        problem = f"names none of {case.names + case.sentinels}"
    return "" if problem is None else f"{case.argv}: {problem}: {err.strip()[:300]}"


def _check(cases: list[Case], capsys) -> None:
    failures = [f for f in (_run_case(c, capsys) for c in cases) if f]
    assert not failures, f"{len(failures)} of {len(cases)} cases:\n" + "\n".join(failures[:20])


# --- configs ------------------------------------------------------------------------------------


def _leaves(value, path=()):
    """(path, value) of every number in a parsed TOML document (paths index lists by position)."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, path + (key,))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _leaves(item, path + (i,))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield path, value


def _schema_leaves(cls, path=()):
    """(path, default) of every int or float field of a config dataclass, nested tables included."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            yield from _schema_leaves(hint, path + (f.name,))
        elif hint in (int, float) or typing.get_args(hint) in ((int, type(None)), (float, type(None))):
            yield path + (f.name,), f.default


def _set(mapping, path, value):
    head, rest = path[0], path[1:]
    if not rest:
        mapping[head] = value
        return
    if isinstance(mapping, dict):
        mapping.setdefault(head, {})
    _set(mapping[head], rest, value)


def _copy(value):
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy(v) for v in value]
    return value


def _preset_commands(tmp: Path):
    """name -> (parsed preset, argv for a config path, sentinels): what each preset is a config of."""
    out_file = tmp / "out-is-a-file"
    out_file.write_text("x")
    no_data = str(tmp / "no-data")
    run_sentinel = ("no data set manifest",)
    presets = {}
    for name in ("crchfl", "hfl", "sfl"):
        data = read_toml(experiments_dir() / f"{name}.toml")
        data["dataset"] = no_data
        presets[name] = (data, lambda p: ["run", str(p), "--out", str(tmp / "run-out")], run_sentinel)
    for name in ("reproduce_quick", "reproduce_full"):
        presets[name] = (read_toml(experiments_dir() / f"{name}.toml"),
                         lambda p: ["reproduce", "--config", str(p), "--out", str(out_file)], ("is a file",))
    for name in ("mobility_quick", "mobility_full"):
        presets[name] = (read_toml(experiments_dir() / f"{name}.toml"),
                         lambda p: ["mobility-study", "--config", str(p), "--out", str(out_file)], ("is a file",))
    return presets


def _config_cases(tmp: Path) -> list[Case]:
    rng = random.Random(SEED)
    cases = []
    folder = tmp / "configs"
    folder.mkdir()

    def write(data, label):
        path = folder / f"{len(cases):04d}-{label}.toml"
        path.write_text(tomli_w.dumps(data), encoding="utf-8")
        return path

    for preset, (data, argv, sentinels) in _preset_commands(tmp).items():
        leaves = dict(_leaves(data))
        per_key = 2 if preset.endswith("_full") else 3  # mutations a key: the full presets repeat the quick ones' keys
        if preset in SCHEMAS:  # every key of the schema, not only those the preset sets
            leaves.update({p: d for p, d in _schema_leaves(SCHEMAS[preset]) if p not in leaves})
        for path, default in leaves.items():
            key = next(str(k) for k in reversed(path) if isinstance(k, str))
            factor_value = path[0] == "factor" and key == "values"  # a study's value of the run setting it names
            if factor_value:
                key = str(data["factor"][path[1]]["key"]).split(".")[-1]
            chosen = ["nan", *rng.sample([v for v in VALUES if v != "nan"], per_key - 1)]  # seeded
            for label in chosen:
                mutated = _copy(data)
                _set(mutated, path, VALUES[label])
                may_pass = label in MAYBE or (label == "inf" and (default == math.inf or factor_value))
                cases.append(Case(argv(write(mutated, label)), (key,), sentinels if may_pass else ()))
        tables = [p for p, v in _dict_paths(data)]
        for table in tables:
            mutated = _copy(data)
            target = mutated
            for k in table:
                target = target[k]
            target["bogus_key"] = 1
            cases.append(Case(argv(write(mutated, "unknown")), ("bogus_key",)))
        text = tomli_w.dumps(data).encode("utf-8")
        for i in range(6):
            at = rng.randrange(len(text))
            path = folder / f"{len(cases):04d}-bytes.toml"
            path.write_bytes(text[:at] + rng.choice([b"\xff", b"\xc3\x28", b"\xe9", b"\x80\x80"]) + text[at:])
            cases.append(Case(argv(path), ("not UTF-8", "malformed TOML")))
        for depth in (40, 3000):
            path = folder / f"{len(cases):04d}-deep.toml"
            path.write_text(tomli_w.dumps(data) + "\ndeep = " + "[" * depth + "]" * depth + "\n", encoding="utf-8")
            cases.append(Case(argv(path), ("nest deeper",)))
    # the configs of simulate and dataset, key by key from their schemas; the scenario 'nowhere' is the sentinel
    from crchfl_sumo.data.generation import GenerateConfig
    from crchfl_sumo.studies.simulate import SimulateConfig

    for command, cls in (("simulate", SimulateConfig), ("dataset", GenerateConfig)):
        for path, default in _schema_leaves(cls):
            for label in ["nan", *rng.sample([v for v in VALUES if v != "nan"], 2)]:
                mutated = {}
                _set(mutated, path, VALUES[label])
                may_pass = label in MAYBE or (label == "inf" and default == math.inf)
                config = str(write(mutated, label))
                argv = [command, "nowhere", "--out", str(tmp / f"{command}-out"), "--config", config]
                cases.append(Case(argv, (path[-1],), ("not a built-in scenario",) if may_pass else ()))
    return cases


def _huge_cases(tmp: Path) -> list[Case]:
    """Every numeric key of every preset and schema set to each huge value once: each is refused, naming the key."""
    cases = []
    folder = tmp / "huge"
    folder.mkdir()
    from crchfl_sumo.data.generation import GenerateConfig
    from crchfl_sumo.studies.simulate import SimulateConfig

    targets = []  # (document, path, argv for a config path)
    for preset, (data, argv, _) in _preset_commands(tmp).items():
        paths = list(dict(_leaves(data)))
        if preset in SCHEMAS:
            paths += [p for p, _ in _schema_leaves(SCHEMAS[preset]) if p not in paths]
        targets += [(data, p, argv) for p in paths]
    for command, cls in (("simulate", SimulateConfig), ("dataset", GenerateConfig)):
        argv = (lambda c: lambda p: [c, "nowhere", "--out", str(tmp / f"{c}-out"), "--config", str(p)])(command)
        targets += [({}, p, argv) for p, _ in _schema_leaves(cls)]
    for data, path, argv in targets:
        key = next(str(k) for k in reversed(path) if isinstance(k, str))
        if path[0] == "factor" and key == "values":
            key = str(data["factor"][path[1]]["key"]).split(".")[-1]
        for label in HUGE:
            mutated = _copy(data)
            _set(mutated, path, VALUES[label])
            config = folder / f"{len(cases):04d}-{label}.toml"
            config.write_text(tomli_w.dumps(mutated), encoding="utf-8")
            cases.append(Case(argv(config), (key,)))
    return cases


def _dict_paths(value, path=()):
    if isinstance(value, dict):
        yield path, value
        for key, item in value.items():
            if isinstance(item, dict):
                yield from _dict_paths(item, path + (key,))


# --- command-line numbers -----------------------------------------------------------------------

NUMBER_VALUES = {
    "nan": True, "inf": True, "-inf": True, "1e308": True, "-1e308": True, str(2**64): True, "abc": True,
    "": True, "9" * 400: True, "0x10": True, "-1": False, "0": False, "1e3": False, "2**31": True,
    str(2**32): False, "0.5": False,
}


def _numeric_actions():
    """(command, option, action) of every argument whose value is a number."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for command, p in sub.choices.items():
        for action in p._actions:
            numeric_default = isinstance(action.default, (int, float)) and not isinstance(action.default, bool)
            if action.option_strings and (numeric_default or action.type in (int, float) or
                                          getattr(action.type, "__module__", "") == "crchfl_sumo.core.numbers"):
                yield command, action.option_strings[-1], action


def test_every_numeric_argument_is_checked_by_a_core_numbers_type():
    actions = list(_numeric_actions())
    assert len(actions) >= 20
    unchecked = [f"{c} {o}" for c, o, a in actions if getattr(a.type, "__module__", "") != "crchfl_sumo.core.numbers"]
    assert not unchecked, f"use a core.numbers type for {unchecked}"


def _templates(tmp: Path) -> dict[str, tuple[list[str], tuple[str, ...]]]:
    """Per command: an argv that fails cheaply right after the arguments are checked, and how it fails."""
    out_file = tmp / "out-is-a-file"
    out_file.write_text("x")
    missing = str(tmp / "missing")
    out = ["--out", str(out_file)]
    return {
        "reproduce": (["reproduce", "--quick", *out], ("is a file",)),
        "simulate": (["simulate", "town01", *out], ("is a file",)),
        "render": (["render", "town01", "--vehicle", "v", *out], ("is a file",)),
        "dataset": (["dataset", "town01", *out], ("is a file",)),
        "train": (["train", missing, *out], ("is a file",)),
        "drive": (["drive", "reference", "--route", "r", *out], ("is a file",)),
        "drive-bench": (["drive-bench", "reference", *out], ("is a file",)),
        "dagger": (["dagger", missing, missing, *out], ("is a file",)),
        "mobility-study": (["mobility-study", "--quick", *out], ("is a file",)),
        "sweep": (["sweep", "crchfl", "--param", "federation.seed=1", *out], ("is a file",)),
        "calibrate": (["calibrate", "--dataset", missing, "--out", str(tmp)], ("is a folder",)),
        "plan": (["plan", "--config", missing], ("config file not found",)),
    }


SWEEP_KEYS = ("federation.seed", "ledger.budget_gb", "sumo.scale", "channel.tx_power_dbm", "train.batch_size",
              "allocation.max_edge_interval", "mobility.coverage_radius_m", "federation.deadline_s", "federation.bogus")
SWEEP_VALUES = {  # TOML value text: refused for sure (True) or perhaps valid for some key (False)
    "nan": True, "-inf": True, "inf": False, "1e308": True, "-1e308": True, "-1": False, "0": False,
    str(2**63 - 1): True,
    '"text"': True, "true": True, "[1.0]": True, "{x = 1}": True, "[" * 40 + "]" * 40: True,
    "[" * 3000 + "]" * 3000: True,
}


def _sweep_cases(tmp: Path) -> list[Case]:
    """sweep --param values (TOML values on the command line); an --out that is a file is the sentinel."""
    out_file = tmp / "sweep-out-is-a-file"
    out_file.write_text("x")
    return [
        Case(["sweep", "crchfl", "--param", f"{key}={value}", "--out", str(out_file)], (key,),
             () if refused or key.endswith("bogus") else ("is a file",))
        for key in SWEEP_KEYS for value, refused in SWEEP_VALUES.items()
    ]


def _number_cases(tmp: Path) -> list[Case]:
    templates = _templates(tmp)
    cases = _sweep_cases(tmp)
    for command, option, _ in _numeric_actions():
        argv, sentinels = templates[command]
        for text, refused in NUMBER_VALUES.items():
            cases.append(Case([*argv, f"{option}={text}"], (option,), () if refused else sentinels))
    return cases


# --- output folders -----------------------------------------------------------------------------

# command -> argv before --out; inputs chosen to fail cheaply should the --out check let a case through
FOLDER_COMMANDS = {
    "simulate": (["simulate", "nowhere"], False),
    "render": (["render", "nowhere", "--vehicle", "v"], False),
    "dataset": (["dataset", "nowhere"], True),
    "dataset-stats": (["dataset-stats", "{empty}"], False),
    "train": (["train", "{missing}"], False),
    "drive": (["drive", "reference", "--route", "nowhere"], False),
    "drive-bench": (["drive-bench", "reference", "--towns", "nowhere"], False),
    "dagger": (["dagger", "{missing}", "{missing}"], False),
    "run": (["run", "{missing}"], True),
    "sweep": (["sweep", "crchfl", "--param", "federation.seed=1"], True),
    "mobility-study": (["mobility-study", "--quick"], True),
    "reproduce": (["reproduce", "--quick"], True),
}
FILE_COMMANDS = {
    "drive-compare": ["drive-compare", "{missing}"],
    "calibrate": ["calibrate", "--dataset", "{missing}"],
}


def _folder_cases(tmp: Path) -> list[Case]:
    from crchfl_sumo.core.outputs import marker_path

    cases = []
    empty = tmp / "empty-input"
    empty.mkdir()
    subs = {"{empty}": str(empty), "{missing}": str(tmp / "missing")}
    a_file = tmp / "a-file"
    a_file.write_text("x")
    states = {"file": a_file, "inside-a-file": a_file / "sub"}
    if os.geteuid() != 0:  # root writes into any folder: no read-only folder to be had
        read_only = tmp / "read-only"
        read_only.mkdir()
        read_only.chmod(0o555)
        states["read-only"] = read_only
        states["inside-read-only"] = read_only / "sub"
    for command, (argv, resumable) in FOLDER_COMMANDS.items():
        argv = [subs.get(a, a) for a in argv]
        own = dict(states)
        other = tmp / f"{command}-other"
        marker_path(other, "train" if command != "train" else "simulate").parent.mkdir()
        marker_path(other, "train" if command != "train" else "simulate").write_text("{}")
        own["other-command"] = other
        if not resumable:
            settings = tmp / f"{command}-settings"
            settings.mkdir()
            marker_path(settings, command).write_text('{"command": "x", "fingerprint": "other"}')
            own["other-settings"] = settings
            stray = tmp / f"{command}-stray"
            stray.mkdir()
            (stray / "notes.txt").write_text("mine")
            own["unmarked-files"] = stray
        for path in own.values():
            cases.append(Case([*argv, "--out", str(path)], ("--out",)))
    for path in (a_file, tmp / "missing", *([states["read-only"]] if "read-only" in states else [])):
        cases.append(Case(["report", str(path)], (f"report {path}",)))  # it rewrites figures in its folder
    for command, argv in FILE_COMMANDS.items():
        argv = [subs.get(a, a) for a in argv]
        for path in (tmp, a_file / "x.png", *([states["inside-read-only"]] if "read-only" in states else [])):
            cases.append(Case([*argv, "--out", str(path)], ("--out",)))
    return cases


# --- the fuzz -----------------------------------------------------------------------------------


def test_fuzz_bad_inputs_exit_2_with_a_message_naming_them(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative defaults (results/, data/) land in the test's folder
    cases = _config_cases(tmp_path) + _number_cases(tmp_path) + _folder_cases(tmp_path)
    assert len(cases) >= 600
    _check(cases, capsys)
    for name in ("run-out", "simulate-out", "dataset-out"):  # refused inputs leave no output folder behind
        assert not (tmp_path / name).exists()


def test_fuzz_huge_values_are_refused_for_every_key(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cases = _huge_cases(tmp_path)
    assert len(cases) >= 3 * 250  # every numeric key of the presets and schemas (263 now), three values each
    _check(cases, capsys)
