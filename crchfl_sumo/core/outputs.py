"""Output folders checked before any work starts: a folder (not a file), writable, and not someone else's.

Every command that writes a folder calls ``prepare_output_dir`` first. It
refuses a path that is a file, a folder it cannot create or write (tried with
a probe file it creates and removes), and a folder that already holds another
command's results, or this command's results from other settings, unless the
user says so (``replace``: the command's --overwrite). It then leaves a marker
``.crchfl-sumo-COMMAND.json`` naming the command and a fingerprint of its
settings, which is how the next call knows whose results the folder holds.

Commands that resume (dataset, run, sweep, mobility-study, reproduce) pass
``resumable``: their own earlier results are theirs to judge (they compare
the stored config and refuse or continue), so only the other checks apply.
A command that continues its own results only when asked (train --resume)
passes ``resume_fingerprint`` too: the fingerprint of the settings a
continuation must keep (all but those it may extend, train's --epochs). The
marker keeps it, and with ``resuming`` a folder whose marker holds the same
one is this command's, whatever the extendable settings were.
``prepare_output_file`` does the same for a command whose output is one file:
it refuses a file that exists unless ``replace`` (--overwrite); the command
then writes it atomically (core/atomic.py), so the old file stays whole until
the new one replaces it.
``output_dir`` wraps ``prepare_output_dir`` around a command's work: when the
work fails before writing anything, it takes back the marker and the folders
it created, so a refused input leaves nothing behind; when the work refuses
its input (a CrchflError) in a folder that had a marker, it puts that marker
back, so the folder still names the settings of the results it holds.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

from crchfl_sumo.core.atomic import TMP_MARK, atomic_write_bytes
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.json_files import write_json

MARKER_PREFIX = ".crchfl-sumo-"
MARKER_SUFFIX = ".json"


def marker_path(folder: str | Path, command: str) -> Path:
    return Path(folder) / f"{MARKER_PREFIX}{command}{MARKER_SUFFIX}"


def fingerprint(settings: Mapping[str, Any], files: Iterable[str | Path] = ()) -> str:
    """sha256 of the settings (JSON, keys sorted) and of the bytes of ``files`` (config files)."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode("utf-8"))
    for path in files:
        digest.update(Path(path).read_bytes())
    return digest.hexdigest()


def markers(folder: str | Path) -> dict[str, dict]:
    """The markers in ``folder`` by command; an unreadable marker reads as ``{}`` (settings unknown)."""
    found = {}
    for path in Path(folder).glob(f"{MARKER_PREFIX}*{MARKER_SUFFIX}"):
        command = path.name[len(MARKER_PREFIX):-len(MARKER_SUFFIX)]
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError, RecursionError):
            data = {}
        found[command] = data if isinstance(data, dict) else {}
    return found


def prepare_output_dir(
    path: str | Path,
    command: str,
    settings_fingerprint: str = "",
    *,
    flag: str = "--out",
    replace: bool = False,
    resumable: bool = False,
    beside: tuple[str, ...] = (),
    resume_fingerprint: str | None = None,
    earlier_resume_fingerprints: tuple[str, ...] = (),
    resuming: bool = False,
) -> Path:
    """Check (and create) ``path`` as ``command``'s output folder before any work; leave its marker.

    ``flag`` names the argument in messages. ``replace``: the user allows
    replacing earlier results (--overwrite). ``resumable``: the command judges
    its own earlier results itself. ``beside``: commands whose results the
    folder may also hold, because it is this command's input (dataset-stats
    writes beside its data set); files without a marker are then expected too.
    ``resume_fingerprint``: the settings a continuation must keep, kept in the
    marker; ``resuming``: this call continues the folder's results, so a marker
    with the same ``resume_fingerprint`` is this command's too, and so is one with
    a fingerprint of ``earlier_resume_fingerprints`` (what earlier versions kept
    for these settings, before an argument became one a resume may change).
    """
    path = Path(path)
    where = f"{flag} {path}"
    if path.exists() and not path.is_dir():
        raise CrchflError(f"{where}: is a file, not a folder; give a folder path (a new one is created)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CrchflError(f"{where}: cannot create the folder ({exc.strerror}); choose a writable place") from None
    _probe_writable(path, where)
    overwrite_hint = "" if resumable else ", or pass --overwrite to replace them"
    found = markers(path)
    others = sorted(c for c in found if c != command and c not in beside)
    if others and not replace:
        raise CrchflError(
            f"{where}: holds the results of `crchfl-sumo {others[0]}`; choose another folder{overwrite_hint}"
        )
    if not resumable and not replace:
        if command in found:
            stored = found[command]
            continues = resuming and resume_fingerprint is not None and (
                stored.get("resume_fingerprint") in (resume_fingerprint, *earlier_resume_fingerprints)
            )
            if stored.get("fingerprint") != settings_fingerprint and not continues:
                raise CrchflError(
                    f"{where}: holds results of `crchfl-sumo {command}` with other settings; "
                    f"choose another folder{overwrite_hint}"
                )
        elif not beside and not found and _holds_files(path):
            raise CrchflError(
                f"{where}: already holds files that are not this command's results; "
                f"choose an empty or new folder{overwrite_hint}"
            )
    marker = {"command": command, "fingerprint": settings_fingerprint}
    if resume_fingerprint is not None:
        marker["resume_fingerprint"] = resume_fingerprint
    write_json(marker_path(path, command), marker)
    return path


@contextlib.contextmanager
def output_dir(path: str | Path, command: str, settings_fingerprint: str = "", **options) -> Iterator[Path]:
    """``prepare_output_dir`` before the ``with`` block's work; undone when the block fails having written nothing."""
    path = Path(path)
    created = [p for p in (path, *path.parents) if not p.exists()]  # deepest first
    marker = marker_path(path, command)
    had_marker = marker.exists()
    try:
        before = marker.read_bytes() if had_marker else None
    except OSError:
        before = None
    prepare_output_dir(path, command, settings_fingerprint, **options)
    try:
        yield path
    except BaseException as exc:
        if not had_marker and [p.name for p in path.iterdir()] == [marker.name]:
            marker.unlink()
            for folder in created:
                folder.rmdir()
        elif before is not None and isinstance(exc, CrchflError):  # a refused input: the results are as they were
            atomic_write_bytes(marker, before)
        raise


def prepare_output_file(path: str | Path, flag: str = "--out", replace: bool = False) -> Path:
    """Check that ``path`` can be written as a file: not a folder, its folder creatable and writable, and
    new unless ``replace`` (the command's --overwrite)."""
    path = Path(path)
    where = f"{flag} {path}"
    if path.is_dir():
        raise CrchflError(f"{where}: is a folder; give the path of the file to write")
    if path.exists() and not replace:
        raise CrchflError(f"{where}: the file exists; choose another path, or pass --overwrite to replace it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CrchflError(f"{where}: cannot create its folder ({exc.strerror}); choose a writable place") from None
    if not path.parent.is_dir():
        raise CrchflError(f"{where}: {path.parent} is a file, not a folder; choose another path")
    _probe_writable(path.parent, where)
    if path.exists() and not os.access(path, os.W_OK):
        raise CrchflError(f"{where}: the file is read-only; fix its permissions or choose another path")
    return path


def check_writable(folder: str | Path, where: str) -> None:
    """A CrchflError naming ``where`` unless ``folder`` is a folder this process can write in."""
    folder = Path(folder)
    if not folder.is_dir():
        what = "is a file, not a folder" if folder.exists() else "no such folder"
        raise CrchflError(f"{where}: {what}; check the path")
    _probe_writable(folder, where)


def _probe_writable(folder: Path, where: str) -> None:
    try:
        fd, probe = tempfile.mkstemp(prefix=f".write-probe{TMP_MARK}", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise CrchflError(
            f"{where}: the folder is not writable ({exc.strerror}); fix its permissions or choose another folder"
        ) from None


def _holds_files(folder: Path) -> bool:
    return any(not entry.name.startswith(MARKER_PREFIX) for entry in folder.iterdir())
