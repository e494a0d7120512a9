"""Atomic file writes: write a temporary file beside the target, then rename it.

A reader (or a resumed run) sees either the old file or the new one, never a
half-written one, whatever moment a run is killed at. Temporaries carry
``TMP_MARK`` in their names, so a resumed run can sweep up what a killed one
left (``remove_stale_temporaries``).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

TMP_MARK = ".partial-"


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``, else delete it.

    The temporary keeps the target's suffix, for writers that pick a format by
    extension (matplotlib, OpenCV's video writer).
    """
    path = Path(path)
    tmp = temporary_beside(path)
    try:
        yield tmp
        with open(tmp, "rb+") as handle:  # on disk before the rename makes it visible
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def temporary_beside(path: str | Path) -> Path:
    """A new empty file next to ``path`` (same folder, so the final rename is atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}{TMP_MARK}", suffix=path.suffix or ".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp_name, 0o666 & ~_umask())  # mkstemp makes 0600; a result file should read like any other
    return Path(tmp_name)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Delete the temporaries an interrupted writer left in ``folder``; return what was removed."""
    removed = []
    for path in Path(folder).glob(f".*{TMP_MARK}*"):
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed
