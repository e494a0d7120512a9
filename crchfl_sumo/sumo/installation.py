"""Where SUMO is: its binaries and its tool scripts, from the eclipse-sumo package (else PATH)."""

from __future__ import annotations

import shutil
from pathlib import Path

from crchfl_sumo.core.errors import CrchflError


def sumo_binary(name: str = "sumo") -> str:
    """Path of a SUMO binary (sumo, netconvert, duarouter ...): the eclipse-sumo package's, else PATH's."""
    try:
        import sumo  # the eclipse-sumo wheel

        candidate = Path(sumo.SUMO_HOME) / "bin" / name
        if candidate.exists():
            return str(candidate)
    except ImportError:
        pass
    found = shutil.which(name)
    if not found:
        raise CrchflError(f"the '{name}' binary was not found; install it with: pip install eclipse-sumo")
    return found


def sumo_tool_script(name: str) -> str:
    """Path of a script in SUMO's tools folder (randomTrips.py ...), from the eclipse-sumo package."""
    try:
        import sumo
    except ImportError:
        raise CrchflError(f"SUMO's {name} needs the eclipse-sumo package: pip install eclipse-sumo") from None
    script = Path(sumo.SUMO_HOME) / "tools" / name
    if not script.is_file():
        raise CrchflError(f"{script} not found; reinstall eclipse-sumo")
    return str(script)
