"""Progress reports: how long-running library code tells its caller how far it is.

Library code never draws bars; it calls the ``Progress`` callback it was
given (if any) with one ``Update``. The CLI turns updates into tqdm bars,
one bar per stage (cli.ProgressBars).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping


@dataclass(frozen=True)
class Update:
    """``done`` of ``total`` units of ``stage`` are finished (total None: not known in advance)."""

    stage: str  # what is under way, e.g. "simulate", "render", "train", "part", "step"
    done: int
    total: int | None
    detail: Mapping[str, str] = field(default_factory=dict)  # short figures shown beside the count


Progress = Callable[[Update], None]


def report(progress: Progress | None, stage: str, done: int, total: int | None, **detail: str) -> None:
    """Send one update to ``progress``; nothing without a callback."""
    if progress is not None:
        progress(Update(stage, done, total, detail))
