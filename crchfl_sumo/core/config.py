"""TOML -> frozen dataclasses, with unknown keys and wrong types rejected; and mappings -> TOML text.

Each module owns the frozen dataclass of its own settings (``channel.ChannelConfig``,
``mobility.MobilityConfig`` ...). This module only knows how to fill any such
dataclass from a mapping, so that a typo in a config file is an error naming the
file and the dotted key, never a silently ignored setting; and how to write a
mapping back as TOML (the configs a run, a sweep or a calibration writes).
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import sys
import types
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised only on Python 3.10
    import tomli as tomllib

import numpy as np

from crchfl_sumo.core.errors import CrchflError

T = TypeVar("T")


def read_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file, turning a missing or malformed file into a CrchflError."""
    path = Path(path)
    if not path.is_file():
        raise CrchflError(f"{path}: config file not found; check the path")
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise CrchflError(f"{path}: malformed TOML ({exc}); fix the syntax at that line") from None


def from_mapping(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``; ``where`` names the source in error messages.

    Missing keys take the dataclass defaults. Nested dataclasses, tuples of
    dataclasses, ``Optional`` and plain scalars are supported; ints are accepted
    where floats are expected.
    """
    if not isinstance(data, Mapping):
        raise CrchflError(f"{where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields))
        raise CrchflError(
            f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}; known keys are: {known}"
        )
    values = {name: _convert(hints[name], data[name], f"{where}.{name}") for name in data}
    try:
        return cls(**values)
    except CrchflError:
        raise
    except (TypeError, ValueError) as exc:
        raise CrchflError(f"{where}: {exc}") from None


def to_mapping(obj: Any) -> Any:
    """Dataclass -> plain dict/list structure (TOML/JSON friendly), the inverse of from_mapping."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_mapping(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_mapping(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _convert(hint: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        errors = []
        for option in options:
            try:
                return _convert(option, value, where)
            except CrchflError as exc:
                errors.append(str(exc))
        raise CrchflError(errors[0])
    if origin is typing.Literal:
        if value not in args:
            raise CrchflError(f"{where}: {value!r} is not one of {', '.join(repr(a) for a in args)}")
        return value
    if dataclasses.is_dataclass(hint):
        return from_mapping(hint, value, where)
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise CrchflError(f"{where}: expected a list, got {type(value).__name__}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            item = args[0]
            return tuple(_convert(item, v, f"{where}[{i}]") for i, v in enumerate(value))
        if origin is tuple and args:
            if len(args) != len(value):
                raise CrchflError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        return [_convert(item, v, f"{where}[{i}]") for i, v in enumerate(value)]
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CrchflError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise CrchflError(f"{where}: expected an integer, got {value!r}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise CrchflError(f"{where}: expected true or false, got {value!r}")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise CrchflError(f"{where}: expected a string, got {value!r}")
        return value
    if hint is Path:
        if not isinstance(value, str):
            raise CrchflError(f"{where}: expected a path string, got {value!r}")
        return Path(value)
    return value


# ------------------------------------------------------------------ writing TOML


def toml_text(mapping: Mapping[str, Any]) -> str:
    """TOML for a mapping of tables, scalars and lists (what configs hold); tomllib reads it back equal."""
    lines: list[str] = []
    _toml_table(mapping, [], lines)
    return "\n".join(lines).strip() + "\n"


def _toml_table(mapping: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    tables = {k: v for k, v in mapping.items() if isinstance(v, Mapping)}
    if path and (len(tables) < len(mapping) or not tables):
        lines += ["", "[" + ".".join(toml_key(p) for p in path) + "]"]
    for key, value in mapping.items():
        if not isinstance(value, Mapping):
            lines.append(f"{toml_key(key)} = {toml_value(value)}")
    for key, value in tables.items():
        _toml_table(value, [*path, key], lines)


def toml_key(key: str) -> str:
    """A bare key where TOML allows one, else a quoted key."""
    return key if key.replace("_", "").replace("-", "").isalnum() and key.isascii() else json.dumps(key)


def toml_value(value: Any) -> str:
    """One value as inline TOML (numpy scalars too)."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        value = float(value)
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + " }"
    raise CrchflError(f"cannot write {value!r} ({type(value).__name__}) to TOML; use a number, string, list or table")


def load_tables(config_path: str | Path | None, types: Mapping[str, type]) -> dict[str, Any]:
    """The tables ``types`` names of a TOML file (read once), each as its dataclass; defaults without a file."""
    data = read_toml(config_path) if config_path is not None else {}
    return {key: from_mapping(cls, data.get(key, {}), f"{config_path}: {key}") for key, cls in types.items()}
