"""Saves that run beside the work: one background thread, one save at a time, in order.

A federation step's files (its log lines, then its checkpoint, then the files
derived from it) go to disk while the loop computes the next step, so that a
slow disk (an fsync that stalls for half a second) no longer stops the loop.
``submit`` first waits for the save before it: saves never overlap and never
reorder, and each reads only the state it was given, which the loop does not
change afterwards (a step works on a copy). An error in a save is raised in
the caller at the next ``submit``, ``wait`` or at the end of the ``with``
block; leaving the block always waits for the save in flight, so the folder
is complete when the caller goes on (or resumes).
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable

log = logging.getLogger(__name__)


class BackgroundSaver:
    """``with BackgroundSaver() as saver: saver.submit(save, state)``: the saves run in order on one thread."""

    def __init__(self, name: str = "save") -> None:
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._pending: Future | None = None

    def submit(self, save: Callable[..., Any], *args: Any) -> None:
        """Wait for the previous save (raising its error), then start ``save(*args)`` in the background."""
        self.wait()
        self._pending = self._pool.submit(save, *args)

    def wait(self) -> None:
        """Block until the save in flight (if any) is on disk; raise its error."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def __enter__(self) -> BackgroundSaver:
        return self

    def __exit__(self, kind, error, trace) -> None:
        try:
            self.wait()
        except Exception as save_error:
            if error is None:
                raise
            log.error("a background save failed too: %s", save_error)  # the caller's error goes on
        finally:
            self._pool.shutdown(wait=True)
