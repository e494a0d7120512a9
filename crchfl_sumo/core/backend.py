"""Where work runs: in this process (``local``) or as Ray tasks (``ray``), behind one small API.

A run trains its vehicles and evaluates its models through an ``Executor``;
a sweep runs its independent runs through one. Both ask for the same few
things: ``put`` a large object once (a vehicle's samples, the test set) and
``map`` a function over argument tuples, results in order; ``imap`` yields
them in order as they finish, so a caller that uses each result and drops it
never holds them all (a thousand trained models are gigabytes).

* ``local``: ``map`` calls the function in this process; ``map(...,
  isolate=True)`` gives every call its own fresh process (spawned, one task
  per child), since libsumo holds one simulation per process. A child that
  dies is retried in a new process up to ``max_retries`` times.
* ``ray``: every call is a Ray task. Ray reruns a task whose worker died up
  to ``max_retries`` times (an exception raised by the task itself is not
  retried: it would raise again). Results are awaited with a timeout: when
  no task finishes within ``task_timeout_s``, the tasks are cancelled and a
  CrchflError says so, so a lost worker or node never hangs a run.

Ray is an optional extra (``pip install 'crchfl-sumo[ray]'``) imported only
when the ray backend is used.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
import multiprocessing
import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Literal, Sequence

from crchfl_sumo.core.cpus import available_cpus
from crchfl_sumo.core.errors import CrchflError
from crchfl_sumo.core.numbers import MAX_JOBS, check_range

log = logging.getLogger(__name__)

OnResult = Callable[[int, Any], None]  # (index of the call, its result)
INSTALL_HINT = "--backend ray needs Ray: pip install 'crchfl-sumo[ray]'"


MAX_RETRIES = 100  # a task whose worker dies this often is broken, not unlucky
MAX_TASK_S = 7 * 86400.0  # the longest wait for one task [wall-clock s]: a week, longer than any task of ours


@dataclass(frozen=True)
class BackendConfig:
    """Execution backend (TOML ``[backend]``; ``--backend``/``--address`` override it).

    kind: "local" (this process; separate processes for sweep runs) or "ray".
    address: Ray only: "" starts a local Ray runtime for the command and stops
        it at the end; "auto" joins the cluster running on this machine
        (``ray start --head``); "HOST:PORT" joins that cluster.
    num_cpus: CPUs of a local Ray runtime, and the number of parallel
        processes of a local sweep; 0 = all of this machine's.
    max_retries: how often a task whose worker process died is run again.
    task_timeout_s: the longest the backend waits for the next task to
        finish before it gives up (cancels the tasks and raises) [s].
    """

    kind: Literal["local", "ray"] = "local"
    address: str = ""
    num_cpus: int = 0
    max_retries: int = 2
    task_timeout_s: float = 3600.0

    def __post_init__(self) -> None:
        if self.kind not in ("local", "ray"):
            raise CrchflError(f"backend.kind: {self.kind!r} is not one of 'local', 'ray'")
        if self.address and self.kind != "ray":
            raise CrchflError(f"backend.address: {self.address!r} joins a Ray cluster; set backend.kind = \"ray\"")
        check_range(self.num_cpus, "backend.num_cpus", 0, MAX_JOBS, "a number of CPUs (0 = all)")
        check_range(self.max_retries, "backend.max_retries", 0, MAX_RETRIES, "a number of retries")
        check_range(self.task_timeout_s, "backend.task_timeout_s", 0, MAX_TASK_S, "seconds", lo_open=True)

    @property
    def workers(self) -> int:
        """Parallel processes of a local isolated map."""
        return self.num_cpus or available_cpus()


def import_ray():
    """The ray module, or a CrchflError that says how to install it."""
    try:
        import ray
    except ImportError:
        raise CrchflError(INSTALL_HINT) from None
    return ray


class Executor:
    """Runs tasks on the backend of ``config``; use as a context manager (a Ray runtime it started is stopped)."""

    def __init__(self, config: BackendConfig) -> None:
        self.config = config
        self._ray = None
        self._started_ray = False

    def __enter__(self) -> "Executor":
        if self.config.kind == "ray":
            ray = import_ray()
            if not ray.is_initialized():
                options: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING}
                if self.config.address:
                    options["address"] = self.config.address
                elif self.config.num_cpus:
                    options["num_cpus"] = self.config.num_cpus
                try:
                    ray.init(**options)
                except ConnectionError as exc:
                    raise CrchflError(
                        f"backend.address {self.config.address!r}: no Ray cluster there ({exc}); "
                        "start one with `ray start --head` or leave --address out for a local runtime"
                    ) from None
                self._started_ray = True
            self._ray = ray
        return self

    def __exit__(self, *exc_info) -> None:
        if self._started_ray:
            self._ray.shutdown()
            self._started_ray = False

    @property
    def is_ray(self) -> bool:
        return self._ray is not None

    def put(self, obj: Any) -> Any:
        """A handle to pass as a task argument in place of ``obj`` (Ray: stored once in the object store)."""
        return self._ray.put(obj) if self.is_ray else obj

    def map(
        self,
        fn: Callable[..., Any],
        args: Sequence[tuple],
        *,
        isolate: bool = False,
        num_cpus: float = 1,
        on_result: OnResult | None = None,
    ) -> list:
        """``[fn(*a) for a in args]`` on the backend, in order.

        ``isolate``: every call in a fresh process (local: spawned children;
        Ray: a worker that exits after the task). ``num_cpus``: CPUs a Ray
        task reserves. ``on_result(i, result)``: called in this process as
        each call finishes (in the order they finish), so that a caller can
        record finished work before the slowest call is done.
        """
        args = list(args)
        if not args:
            return []
        if self.is_ray:
            results = [None] * len(args)
            for i, result in self._ray_results(fn, args, isolate, num_cpus):
                results[i] = result
                if on_result is not None:
                    on_result(i, result)
            return results
        if isolate:
            return _map_processes(fn, args, self.config, on_result)
        results = []
        for i, a in enumerate(args):
            results.append(fn(*a))
            if on_result is not None:
                on_result(i, results[-1])
        return results

    def imap(self, fn: Callable[..., Any], args: Sequence[tuple], *, num_cpus: float = 1) -> Iterator:
        """``fn(*a) for a in args`` on the backend, yielded in order.

        Local: each call runs when its result is asked for. Ray: every call is
        a task from the first request on; a result is fetched when its task
        finishes and released from the object store as it is handed over, so a
        caller that drops each result before asking for the next holds only
        those that finished ahead of an earlier one. Closing the iterator early
        cancels the tasks still running.
        """
        args = list(args)
        if not self.is_ray:
            return (fn(*a) for a in args)
        return _in_order(self._ray_results(fn, args, False, num_cpus))

    def _ray_results(self, fn, args: list[tuple], isolate: bool, num_cpus: float) -> Iterator[tuple[int, Any]]:
        """(index, result) of every call as its task finishes; each result is fetched once."""
        ray, cfg = self._ray, self.config
        options: dict[str, Any] = {"max_retries": cfg.max_retries, "num_cpus": num_cpus}
        if isolate:
            options["max_calls"] = 1  # the worker process exits after one task: one SUMO per process
        remote = ray.remote(**options)(fn)
        pending = [remote.remote(*a) for a in args]
        index = {ref: i for i, ref in enumerate(pending)}  # a ref leaves it when its result is handed over
        timeout = None if math.isinf(cfg.task_timeout_s) else cfg.task_timeout_s
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=timeout)
                if not done:
                    raise CrchflError(
                        f"no Ray task finished within backend.task_timeout_s = {cfg.task_timeout_s:g} s "
                        f"({len(pending)} of {len(args)} unfinished); a worker or node may be lost: check "
                        "`ray status`, or raise backend.task_timeout_s for longer tasks"
                    )
                for ref in done:
                    yield index.pop(ref), ray.get(ref)  # a failed task raises now, not after the others
        except ray.exceptions.RayTaskError as exc:  # the task itself raised: the same error here
            _cancel(ray, pending)
            cause = getattr(exc, "cause", None)
            if isinstance(cause, CrchflError):
                raise CrchflError(str(cause)) from None
            raise
        except ray.exceptions.RayError as exc:  # a worker or node died more often than retried, ran out of memory
            _cancel(ray, pending)
            raise CrchflError(
                f"a Ray task was lost ({type(exc).__name__}: {exc}) after backend.max_retries = {cfg.max_retries} "
                "reruns; check memory and the nodes (`ray status`) or raise backend.max_retries"
            ) from None
        except BaseException:  # the caller stopped early (GeneratorExit) or was interrupted
            _cancel(ray, pending)
            raise


def _in_order(results: Iterator[tuple[int, Any]]) -> Iterator:
    """The results of (index, result) pairs that come in any order, yielded in index order as soon as each can be."""
    ahead: dict[int, Any] = {}  # results that finished before an earlier one
    following = 0
    try:
        for i, result in results:
            ahead[i] = result
            while following in ahead:
                yield ahead.pop(following)
                following += 1
    finally:
        results.close()  # cancels the tasks still running when the caller stops early


def _cancel(ray, refs) -> None:
    for ref in refs:
        ray.cancel(ref, force=True)


# ------------------------------------------------------------------ local processes


def _map_processes(fn, args: list[tuple], config: BackendConfig, on_result: OnResult | None = None) -> list:
    """Each call in its own spawned process, ``config.workers`` at a time; a dead child's call is retried.

    A call that raises cancels the calls not yet started (those running are
    waited for) and the error is raised here.
    """
    results: dict[int, Any] = {}
    attempts = dict.fromkeys(range(len(args)), 0)
    options: dict[str, Any] = {"mp_context": multiprocessing.get_context("spawn")}
    if sys.version_info >= (3, 11):  # older: children are reused, one task after the other (SUMO is closed between)
        options["max_tasks_per_child"] = 1
    while len(results) < len(args):
        todo = [i for i in range(len(args)) if i not in results]
        with cf.ProcessPoolExecutor(min(config.workers, len(todo)), **options) as pool:
            futures = {pool.submit(fn, *args[i]): i for i in todo}
            try:
                for future in cf.as_completed(futures):
                    i = futures[future]
                    try:
                        results[i] = future.result()
                    except cf.process.BrokenProcessPool:
                        # a child died (killed, out of memory): the pool is broken, so every unfinished
                        # call of it, the dead one's and those beside it, is tried again in a new pool
                        attempts[i] += 1
                        if attempts[i] > config.max_retries:
                            raise CrchflError(
                                f"a worker process died {attempts[i]} times running task {i} and backend."
                                f"max_retries = {config.max_retries}; check memory or raise backend.max_retries"
                            ) from None
                        continue
                    if on_result is not None:
                        on_result(i, results[i])
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)  # not the queued calls too before raising
                raise
        if len(results) < len(args):
            log.info("a worker process died; retrying %d task(s) in new processes", len(args) - len(results))
    return [results[i] for i in range(len(args))]
