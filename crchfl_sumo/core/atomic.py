"""Atomic file writes: write a temporary file beside the target, then rename it.

A reader (or a resumed run) sees either the old file or the new one, never a
half-written one, whatever moment a run is killed at. Temporaries carry
``TMP_MARK`` in their names, so a resumed run can sweep up what a killed one
left (``remove_stale_temporaries``).

A file a resume reads (a checkpoint) is written with ``atomic_path_keeping_previous``:
the file it replaces becomes ``NAME.prev.SUFFIX`` (``previous_path``), and
``read_latest`` reads that one when the latest is damaged, so one empty,
truncated or corrupt file costs one step of work, not the run.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from pathlib import Path
from typing import Callable, Iterator, TypeVar

from crchfl_sumo.core.errors import CrchflError

log = logging.getLogger(__name__)

T = TypeVar("T")
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


def previous_path(path: str | Path) -> Path:
    """Where ``atomic_path_keeping_previous`` keeps the file it replaced: checkpoint.pt -> checkpoint.prev.pt."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


@contextlib.contextmanager
def atomic_path_keeping_previous(path: str | Path) -> Iterator[Path]:
    """``atomic_path``, and the file it replaces becomes ``previous_path(path)``.

    The old file is renamed aside right before the new one is renamed in; killed
    between the two renames, the folder holds the previous copy only, which
    ``read_latest`` reads.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        yield tmp
        if path.exists():
            os.replace(path, previous_path(path))


def read_latest(path: str | Path, read: Callable[[Path], T], what: str, fix: str) -> tuple[T, Path]:
    """``(read(path), path)``; when ``read`` refuses ``path`` (a CrchflError: missing, empty, truncated,
    damaged) and the previous copy exists, ``(read(previous), previous)`` with a warning naming both,
    and the refused file is removed (a resume leaves no damaged file behind).

    With neither readable, a CrchflError gives both reasons and ``fix``; ``what`` names the file's kind.
    """
    path = Path(path)
    previous = previous_path(path)
    try:
        return read(path), path
    except CrchflError as latest:
        if not previous.is_file():
            raise
        try:
            value = read(previous)
        except CrchflError as before:
            raise CrchflError(f"{latest}; the previous {what} is no better ({before}); {fix}") from None
        # The damaged file goes: the next save keeping its previous copy would otherwise rename it over
        # the good one, and a later resume would find two damaged files.
        path.unlink(missing_ok=True)
        log.warning("%s; removed it and resuming from %s (the %s before it)", latest, previous, what)
        return value, previous


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


def remove_stale_temporaries(folder: str | Path, recursive: bool = False) -> list[Path]:
    """Delete the temporaries an interrupted writer left in ``folder`` (and its subfolders with ``recursive``);
    return what was removed."""
    removed = []
    pattern = f".*{TMP_MARK}*"
    for path in Path(folder).rglob(pattern) if recursive else Path(folder).glob(pattern):
        path.unlink(missing_ok=True)
        removed.append(path)
    return removed
