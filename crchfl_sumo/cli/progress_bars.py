"""How the command line shows the library's progress: ProgressBars, the only progress display."""

from __future__ import annotations

import math
import sys
import time


class ProgressBars:
    """The library's progress updates (core.progress) as tqdm bars: one bar a stage, its details beside it.

    Without a terminal (a log file, CI), where bars are not drawn, a plain line goes to stderr instead: at
    each new stage, at a stage's end, and at most every ``PLAIN_EVERY_S`` seconds in between.
    The CLI owns all progress display; use as a context manager so the last bar closes.
    """

    PLAIN_EVERY_S = 60.0

    def __init__(self, unit: str, stream=None) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self._unit = unit
        self._stage: str | None = None
        self._bar = None
        self._stream = stream if stream is not None else sys.stderr
        self._plain = not (hasattr(self._stream, "isatty") and self._stream.isatty())
        self._last_line_s = -math.inf
        self._ended = False  # the current stage's last line is out

    def __call__(self, update) -> None:
        if self._plain:
            self._line(update)
            return
        if update.stage != self._stage or self._bar is None or update.done < self._bar.n:
            self.close()
            self._bar = self._tqdm(total=update.total, unit=self._unit, desc=update.stage, dynamic_ncols=True,
                             leave=False, disable=None)
            self._stage = update.stage
        self._bar.update(update.done - self._bar.n)
        if update.detail:
            self._bar.set_postfix(update.detail)

    def _line(self, update) -> None:
        now = time.monotonic()
        new_stage = update.stage != self._stage
        finished = update.total is not None and update.done >= update.total and (new_stage or not self._ended)
        if new_stage or finished or now - self._last_line_s >= self.PLAIN_EVERY_S:
            of = "" if update.total is None else f"/{update.total}"
            detail = "".join(f", {k} {v}" for k, v in update.detail.items())
            print(f"{update.stage}: {update.done}{of} {self._unit}{detail}", file=self._stream, flush=True)
            self._stage, self._last_line_s = update.stage, now
            self._ended = update.total is not None and update.done >= update.total

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "ProgressBars":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
