"""A user's .sumocfg read into sumo command-line options, and a .sumocfg written for a network.

A user's configuration is read, not trusted blindly: options that
only sumo-gui knows are dropped (sumo would refuse them), and so are the TraCI
server's (a remote port would make sumo wait for a client), file options are made
absolute (so relative paths keep working from any directory), and output-file
options are dropped (so running here never overwrites the user's own results).
What remains becomes command-line options for sumo/libsumo.
"""

from __future__ import annotations

import functools
import logging
import math
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from sumolib.miscutils import parseTime

from crchfl_sumo.core.atomic import atomic_write_text
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.sumo.installation import sumo_binary

log = logging.getLogger(__name__)

# Option sections a run here leaves out: sumo-gui's own, and the TraCI server's (remote-port,
# num-clients): with a port, sumo waits for a client that never connects.
DROPPED_SECTIONS = ("gui_only", "traci_server")


@dataclass(frozen=True)
class _OptionSpec:
    section: str
    type: str


@functools.lru_cache(maxsize=1)
def _sumo_option_specs() -> tuple[dict[str, _OptionSpec], dict[str, str]]:
    """Every option sumo knows (from its own template): name -> spec, synonym -> name."""
    with tempfile.TemporaryDirectory() as tmp:
        template = Path(tmp) / "template.xml"
        subprocess.run(
            [sumo_binary(), "--save-template", str(template)],
            check=True,
            capture_output=True,
        )
        root = ET.parse(template).getroot()
    specs: dict[str, _OptionSpec] = {}
    synonyms: dict[str, str] = {}
    for section in root:
        for option in section:
            specs[option.tag] = _OptionSpec(section.tag, option.get("type", ""))
            for synonym in (option.get("synonymes") or "").split():
                synonyms[synonym] = option.tag
    return specs, synonyms


def sumo_options_from_config(cfg_path: Path) -> tuple[list[str], list[str]]:
    """Sanitised sumo command-line options from a .sumocfg, and the names of dropped options."""
    if not cfg_path.is_file():
        raise CrchflError(f"{cfg_path}: SUMO configuration not found; check the path")
    try:
        root = ET.parse(cfg_path).getroot()
    except ET.ParseError as exc:
        raise CrchflError(f"{cfg_path}: malformed XML ({exc}); fix the file") from None
    specs, synonyms = _sumo_option_specs()
    base = cfg_path.parent
    options: list[str] = []
    dropped: list[str] = []
    for element in root.iter():
        value = _config_value(element)
        if value is None or element is root:
            continue
        name = synonyms.get(element.tag, element.tag)
        spec = specs.get(name)
        if spec is None or spec.section in DROPPED_SECTIONS:
            dropped.append(name)
            if spec is not None and spec.section == "traci_server":
                log.warning("%s: ignoring <%s>: a TraCI server would wait for a client that never connects "
                            "(crchfl-sumo drives SUMO itself)", cfg_path.name, element.tag)
            continue
        if spec.type == "FILE":
            if spec.section in ("output", "report") or name in ("save-configuration", "save-template", "save-schema"):
                dropped.append(name)
                continue
            value = ",".join(str(resolved_path(base / p)) for p in _split_files(value))
            missing = [p for p in value.split(",") if p and spec.section == "input" and not Path(p).exists()]
            if missing:
                raise CrchflError(
                    f"{cfg_path}: <{element.tag}> names {missing[0]}, which does not exist; fix the path"
                )
        options.append(f"--{name}={value}")
    if dropped:
        log.info("%s: ignoring options %s (GUI-only, TraCI server, unknown, or output files)", cfg_path.name, dropped)
    return options, dropped


def resolved_path(path: Path) -> Path:
    """``path`` made absolute with its links followed; a loop of symbolic links is a CrchflError."""
    try:
        return path.resolve()
    except (RuntimeError, OSError) as exc:  # Python 3.11/3.12 raise RuntimeError for a loop, 3.13 OSError
        raise CrchflError(f"{path}: cannot be followed ({exc}); point to the file itself, not to a loop of links") from None


def _config_value(element: ET.Element) -> str | None:
    """An option's value in any form sumo reads: ``value="..."``, ``v="..."`` or the element's text."""
    value = element.get("value", element.get("v"))
    if value is None and len(element) == 0 and element.text and element.text.strip():
        value = element.text.strip()
    return value


def _split_files(value: str) -> list[str]:
    # sumo separates file lists by commas only: a space may be part of a path
    return [p.strip() for p in value.split(",") if p.strip()]


def sumo_time_s(text: str, cfg_path: Path, option: str) -> float:
    """A SUMO time value in seconds: plain seconds or [[days:]hours:]minutes:seconds (sumolib's parseTime)."""
    try:
        seconds = parseTime(text) if text.count(":") <= 3 else None
    except (ValueError, IndexError):
        seconds = None
    if seconds is None:
        raise CrchflError(f"{cfg_path}: <{option}> {text!r} is not a time; give seconds")
    if not math.isfinite(seconds):
        raise CrchflError(f"{cfg_path}: <{option}> {text!r} is not a finite time; give seconds")
    return seconds


def _option_value(options: list[str] | tuple[str, ...], name: str) -> str | None:
    prefix = f"--{name}="
    values = [o[len(prefix):] for o in options if o.startswith(prefix)]
    return values[-1] if values else None


def write_sumocfg(folder: Path, net: Path, routes: Sequence[Path] = ()) -> Path:
    """A .sumocfg in ``folder``, named after the network (N.net.xml[.gz] -> N.sumocfg, so the scenario is N),
    naming the network and route files by absolute path; each file must exist. It sets no step length:
    SUMO's 1 s. Returns its path."""
    from xml.sax.saxutils import quoteattr

    for given, what in ((net, "--net"), *((r, "--routes") for r in routes)):
        if not Path(given).is_file():
            raise CrchflError(
                f"{what} {given}: no such file; give a SUMO network (.net.xml or .net.xml.gz) and route files"
            )
    files = ",".join(str(Path(r).resolve()) for r in routes)
    text = (f"<configuration>\n  <input>\n    <net-file value={quoteattr(str(Path(net).resolve()))}/>\n"
            + (f"    <route-files value={quoteattr(files)}/>\n" if routes else "")
            + "  </input>\n</configuration>\n")
    path = Path(folder) / f"{Path(net).name.removesuffix('.gz').removesuffix('.xml').removesuffix('.net')}.sumocfg"
    atomic_write_text(path, text)
    return path
