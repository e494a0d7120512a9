"""matplotlib for files: the Agg backend (no screen needed) and atomic figure saving.

matplotlib is imported on first use, not at import time: it is slow to load
and most commands draw nothing.
"""

from __future__ import annotations

from pathlib import Path

from crchfl_sumo.core.atomic import atomic_path


def pyplot():
    """matplotlib.pyplot on the Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 120) -> Path:
    """Save ``fig`` atomically (temporary file, then rename; format from the suffix), close it; the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight", format=path.suffix.lstrip(".") or "png")
    pyplot().close(fig)
    return path
