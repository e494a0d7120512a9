"""JSON files of results folders, read and written in one way: a damaged file is a CrchflError
naming the file and the fix, and a file is written whole or not at all (core.atomic)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.errors import CrchflError


def read_json(path: str | Path, fix: str = "rerun the command that writes it") -> Any:
    """The JSON value in ``path``; a missing, unreadable or malformed file is a CrchflError ending in ``fix``."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CrchflError(f"{path}: not readable JSON ({exc}); {fix}") from None


def read_json_object(path: str | Path, keys: tuple[str, ...], fix: str = "rerun the command that writes it") -> dict:
    """read_json of a file that must hold an object with ``keys``."""
    value = read_json(path, fix)
    if not isinstance(value, dict) or any(key not in value for key in keys):
        missing = [k for k in keys if not isinstance(value, dict) or k not in value]
        raise CrchflError(f"{path}: lacks {', '.join(missing)}; {fix}")
    return value


def write_json(path: str | Path, value: Any, indent: int | None = 2) -> None:
    """``value`` as JSON in ``path``, atomically, with a final newline."""
    atomic_write_text(path, json.dumps(value, indent=indent) + "\n")
