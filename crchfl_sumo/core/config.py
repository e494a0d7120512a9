"""TOML -> frozen dataclasses, with unknown keys and wrong types rejected; and mappings -> TOML text.

Each module owns the frozen dataclass of its own settings (``channel.ChannelConfig``,
``mobility.MobilityConfig`` ...). This module only knows how to fill any such
dataclass from a mapping, so that a typo in a config file is an error naming the
file and the dotted key, never a silently ignored setting; and how to write a
mapping back as TOML (the configs a run, a sweep or a calibration writes).
"""

from __future__ import annotations

import dataclasses
import math
import re
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
import tomli_w

from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import check_seed

T = TypeVar("T")


MAX_DEPTH = 32  # tables and lists nested deeper than this are no config of ours
_TOO_DEEP = f"tables or lists nest deeper than {MAX_DEPTH} levels; no setting needs that, flatten it"


def read_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; a missing, unreadable, non-UTF-8, malformed or absurdly nested file is a CrchflError."""
    path = Path(path)
    if not path.is_file():
        raise CrchflError(f"{path}: config file not found; check the path")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CrchflError(f"{path}: cannot read the config file ({exc.strerror}); check its permissions") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CrchflError(
            f"{path}: not UTF-8 text (byte {exc.start} is {data[exc.start:exc.start + 1]!r}); save the config as UTF-8"
        ) from None
    try:
        return loads_toml(text, str(path))
    except tomllib.TOMLDecodeError as exc:
        raise CrchflError(f"{path}: malformed TOML ({exc}); fix the syntax at that line") from None


def loads_toml(text: str, where: str) -> dict[str, Any]:
    """``tomllib.loads`` with nesting past ``MAX_DEPTH`` a CrchflError naming ``where`` (a TOMLDecodeError passes)."""
    try:
        table = tomllib.loads(text)
    except RecursionError:
        raise CrchflError(f"{where}: {_TOO_DEEP}") from None
    if nesting_depth(table) > MAX_DEPTH:
        raise CrchflError(f"{where}: {_TOO_DEEP}")
    return table


def nesting_depth(value: Any) -> int:
    """How deep tables and lists nest in ``value`` (a scalar: 0, ``{"a": 1}``: 1); without recursion."""
    depth, level = 0, [value]
    while True:
        containers = [item for item in level if isinstance(item, (Mapping, list, tuple))]
        if not containers:
            return depth
        depth += 1
        level = [v for c in containers for v in (c.values() if isinstance(c, Mapping) else c)]


def from_mapping(cls: type[T], data: Mapping[str, Any], where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``; ``where`` names the source in error messages.

    Missing keys take the dataclass defaults. Nested dataclasses, tuples of
    dataclasses, ``Optional`` and plain scalars are supported; ints are accepted
    where floats are expected. Checks every field gets, whatever its class:
    a float is finite (``inf`` only where the default is ``inf``, i.e. "no
    limit"; NaN never), and a field named ``seed`` or ``*_seed`` is a seed
    (core.numbers). Physical ranges are each dataclass's own ``__post_init__``.
    A field whose name cannot be a key's (``class``, a Python keyword) names its key in its
    metadata: ``field(metadata={KEY: "class"})``.
    """
    if not isinstance(data, Mapping):
        raise CrchflError(f"{where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {_key(f): f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        known = ", ".join(sorted(fields))
        raise CrchflError(
            f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}; known keys are: {known}"
        )
    values = {}
    for name in data:
        value = _convert(hints[fields[name].name], data[name], f"{where}.{name}")
        _check_finite(value, f"{where}.{name}", allow_inf=fields[name].default == math.inf)
        if (name == "seed" or name.endswith("_seed")) and value is not None:
            check_seed(value, f"{where}.{name}")
        values[fields[name].name] = value
    try:
        return cls(**values)
    except (CrchflError, TypeError, ValueError) as exc:  # the dataclass's own checks (__post_init__)
        raise CrchflError(_located(str(exc), where)) from None


KEY = "key"  # a field's metadata entry naming its key where the field's name cannot be it
# a field's metadata entry: leave the field out of a mapping while it holds its default (a setting added later,
# so that what was written before it existed, checkpoints and summaries, stays as it was)
OMIT_DEFAULT = "omit_default"


def _key(f: dataclasses.Field) -> str:
    return f.metadata.get(KEY, f.name)


def _located(message: str, where: str) -> str:
    """``message`` of a dataclass's own check, led by ``where`` (the file and table) unless it names it already.

    A check names its key by the dataclass's table ("federation.deadline_s: ...");
    where ``where`` ends in that table ("run.toml.federation"), the two are joined
    ("run.toml.federation.deadline_s: ..."), else ``where`` leads ("run.toml: ...").
    """
    if message.startswith(where):
        return message
    table = re.match(r"[A-Za-z_]\w*(?=[.:\s])", message)
    head = where[: len(where) - len(table.group())] if table else ""
    if table and where.endswith(table.group()) and message[table.end()] in ".:" and not head[-1:].isalnum():
        return head + message
    return f"{where}: {message}"


def _check_finite(value: Any, where: str, allow_inf: bool) -> None:
    """A CrchflError for a NaN or infinite float in ``value`` (a scalar or a list of them)."""
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _check_finite(item, f"{where}[{i}]", allow_inf)
    elif isinstance(value, float) and not math.isfinite(value) and not (allow_inf and value == math.inf):
        fix = "give a finite number or inf (no limit)" if allow_inf else "give a finite number"
        raise CrchflError(f"{where}: {value} is not allowed; {fix}")


def to_mapping(obj: Any) -> Any:
    """Dataclass -> plain dict/list structure (TOML/JSON friendly), the inverse of from_mapping."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            _key(f): to_mapping(getattr(obj, f.name))
            for f in dataclasses.fields(obj)
            if not (f.metadata.get(OMIT_DEFAULT) and getattr(obj, f.name) == f.default)
        }
    if isinstance(obj, (list, tuple)):
        return [to_mapping(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


_MISSING = object()  # a key one side lacks: unequal to any value


def changed_keys(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two mappings (nested ones compared key by key; a key
    one of them lacks counts): what a refusal to resume names, so that the user sees which setting moved."""
    changed = []
    for key in sorted(set(old) | set(new), key=str):
        a, b, name = old.get(key, _MISSING), new.get(key, _MISSING), f"{prefix}{key}"
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            changed += changed_keys(a, b, f"{name}.")
        elif a != b:
            changed.append(name)
    return changed


def changed_keys_text(old: Mapping[str, Any], new: Mapping[str, Any], shown: int = 4) -> str:
    """changed_keys as words: the first ``shown`` keys, and how many more."""
    keys = changed_keys(old, new)
    more = f" and {len(keys) - shown} more" if len(keys) > shown else ""
    return ", ".join(keys[:shown]) + more


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
    """TOML for a mapping of tables, scalars and lists (what configs hold), written by tomli-w; reads back equal.

    numpy scalars and tuples are turned into their Python equivalents first (tomli-w knows neither).
    """
    try:
        return tomli_w.dumps(_plain(mapping))
    except TypeError as exc:
        raise CrchflError(f"cannot write this config as TOML ({exc}); use numbers, strings, lists and tables") from None


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def load_tables(config_path: str | Path | None, types: Mapping[str, type]) -> dict[str, Any]:
    """The tables ``types`` names of a TOML file (read once), each as its dataclass; defaults without a file."""
    data = read_toml(config_path) if config_path is not None else {}
    return {key: from_mapping(cls, data.get(key, {}), f"{config_path}: {key}") for key, cls in types.items()}


def set_path(mapping: dict, keys: tuple[str, ...], value: Any, where: str) -> dict:
    """A copy of ``mapping`` with the table path ``keys`` set to ``value`` (missing tables are created)."""
    out = dict(mapping)
    head, rest = keys[0], keys[1:]
    if not rest:
        out[head] = value
        return out
    table = out.get(head, {})
    if not isinstance(table, dict):
        raise CrchflError(f"{where}: {head!r} is a value, not a table, in the config")
    out[head] = set_path(table, rest, value, where)
    return out


def deep_merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` laid on top; tables merge key by key, other values are replaced."""
    merged = dict(base)
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged
