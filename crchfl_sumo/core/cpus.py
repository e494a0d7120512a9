"""The CPUs this process may use, and how torch's OpenMP threads wait for work.

Thread counts follow the affinity mask (``os.sched_getaffinity``: what a
container, ``taskset`` or a batch scheduler grants), divided among the parts
that run side by side. They never follow the momentary load: a different
number of threads sums floating-point reductions in a different order, and
the same config and seed must give the same metrics.

Where torch's threads run and how they wait change no result, only its speed.
While a process trains or evaluates on every CPU of its mask, each of its
threads is pinned to a CPU of its own (``pinned_threads``): left free, the
kernel sometimes put two of them on one core beside another process's work,
and a thread that spins at a barrier (OpenMP's wait, oneDNN's bfloat16 weight
gradients) then holds the core that the thread it waits for needs; beside one
busy process bfloat16 training fell to 0.4 of one thread alone, and pinned it
keeps 0.7 to 0.85 (docs/benchmarks.md). Pinned threads keep OpenMP's
spinning wait, which is the faster one on an idle machine and, pinned, beside
a busy one too. Where threads cannot be pinned (no affinity calls, or parts
that share the CPUs with 2 or more threads each) and other processes keep at
least ``BUSY_CPUS`` CPUs busy as a command starts, waiting threads sleep
instead (``OMP_WAIT_POLICY=PASSIVE``).

Two defaults of native libraries cost this workload more than they give, so
every command turns them off where the user has not set them
(``settle_native_libraries``; docs/benchmarks.md): OpenCV's worker threads,
which split each 64 x 128 image operation and spend their time waking and
waiting, and numpy's MADV_HUGEPAGE on large arrays, whose first touch stalls
in the kernel's memory compaction where transparent hugepages are 'madvise'
(numpy issue 31590). Neither changes a result.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import threading
import time
from typing import Iterator, MutableMapping

log = logging.getLogger(__name__)

BUSY_CPUS = 0.5  # CPUs kept busy by other processes from which waiting threads sleep
SAMPLE_S = 0.1  # how long the start of a command watches the CPUs
WAIT_POLICY = "OMP_WAIT_POLICY"
STAT_PATH = "/proc/stat"
TASKS_PATH = "/proc/self/task"  # one entry per thread of this process (Linux)
PARALLEL_GRAIN = 32768  # elements from which torch splits an elementwise operation over its threads


def available_cpus() -> int:
    """The CPUs this process may run on: its affinity mask where the system has one."""
    return len(_affinity())


def threads_per_part(parts: int) -> int:
    """Torch threads for each of ``parts`` processes that share this process's CPUs (at least 1)."""
    return max(1, available_cpus() // max(1, parts))


def cpu_times(stat_text: str, cpus: set[int]) -> tuple[int, int]:
    """(busy, total) clock ticks of ``cpus`` summed from the text of /proc/stat.

    A ``cpuN`` line holds user, nice, system, idle, iowait, irq, softirq,
    steal, ...; idle and iowait are the ticks in which the CPU had nothing to run.
    """
    busy = total = 0
    for line in stat_text.splitlines():
        name, *fields = line.split()
        if not (name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus):
            continue
        ticks = [int(value) for value in fields[:8]]
        total += sum(ticks)
        busy += sum(ticks) - ticks[3] - ticks[4]
    return busy, total


def busy_cpus(sample_s: float = SAMPLE_S) -> float | None:
    """How many of this process's CPUs other processes kept busy over ``sample_s``; None where unknown.

    This process sleeps while it watches, so what it sees is the others' load.
    """
    cpus = _affinity()
    try:
        with open(STAT_PATH) as stat:
            before = cpu_times(stat.read(), cpus)
        time.sleep(sample_s)
        with open(STAT_PATH) as stat:
            after = cpu_times(stat.read(), cpus)
    except OSError:
        return None
    total = after[1] - before[1]
    if total <= 0:
        return None
    return len(cpus) * (after[0] - before[0]) / total


def choose_wait_policy(
    environ: MutableMapping[str, str] = os.environ, busy: float | None = None, parts: int = 1
) -> str | None:
    """Let torch's waiting threads sleep when other processes keep the CPUs busy and the threads
    cannot be pinned: the policy set, or None.

    ``parts``: the processes the command runs side by side. Acts only before
    torch is imported (OpenMP reads the policy once, when it loads) and only
    where the user has set no policy or thread count of their own. ``busy``
    (CPUs) is measured when not given.
    """
    if "torch" in sys.modules or WAIT_POLICY in environ or "OMP_NUM_THREADS" in environ:
        return None
    threads = threads_per_part(parts)
    if threads < 2:
        return None  # one thread: nothing waits
    if threads == available_cpus() and can_pin_threads():
        return None  # pinned while they work (pinned_threads), where spinning is the faster wait
    if busy is None:
        busy = busy_cpus()
    if busy is None or busy < BUSY_CPUS:
        return None
    environ[WAIT_POLICY] = "PASSIVE"
    log.info("%.1f of %d CPUs busy with other processes: torch's waiting threads sleep", busy, available_cpus())
    return "PASSIVE"


def can_pin_threads() -> bool:
    """Whether this system lets a process set the CPUs of each of its threads (Linux)."""
    return hasattr(os, "sched_setaffinity") and os.path.isdir(TASKS_PATH)


def pin_plan(main: int, others: list[int], cpus: list[int]) -> dict[int, set[int]]:
    """The CPU of each thread: ``main`` on the first of ``cpus``, ``others`` (by id) in turn on the rest.

    OpenMP starts its workers together, so their ids follow one another and any
    len(cpus) - 1 of them in a row land on different CPUs, whatever idle native
    threads (a BLAS pool) come before them.
    """
    plan = {main: {cpus[0]}}
    rest = cpus[1:]
    for i, tid in enumerate(sorted(others)):
        plan[tid] = {rest[i % len(rest)]}
    return plan


_pinned_depth = 0  # pinned_threads blocks open in this process


@contextlib.contextmanager
def pinned_threads() -> Iterator[bool]:
    """While torch works on every CPU of this process, keep each of its threads on a CPU of its own.

    Yields whether the threads are pinned: not with one thread, with fewer
    threads than CPUs (parts that share the CPUs), inside another such block,
    or where the system cannot pin. The main thread goes on the first CPU and
    torch's native worker threads on the others; Python threads (a background
    saver) are left free. On leaving, every thread gets its CPUs back, and a
    thread started inside gets the main thread's.
    """
    global _pinned_depth
    import torch  # here, not above: this module is loaded before torch, to set OpenMP's environment

    threads = torch.get_num_threads()
    if _pinned_depth or threads < 2 or not can_pin_threads() or len(_affinity()) != threads:
        yield False
        return
    cpus = sorted(_affinity())
    torch.ones(2 * threads * PARALLEL_GRAIN).sum()  # one parallel region: OpenMP's workers exist from here on
    main = threading.get_native_id()
    python_threads = {t.native_id for t in threading.enumerate()}
    saved = {tid: _thread_affinity(tid) for tid in _thread_ids()}
    _set_affinities(pin_plan(main, [tid for tid in saved if tid not in python_threads], cpus))
    _pinned_depth += 1
    try:
        yield True
    finally:
        _pinned_depth -= 1
        home = saved.get(main) or set(cpus)
        _set_affinities({tid: saved.get(tid) or home for tid in _thread_ids()})


def _thread_ids() -> list[int]:
    try:
        return [int(name) for name in os.listdir(TASKS_PATH)]
    except OSError:
        return []


def _thread_affinity(tid: int) -> set[int] | None:
    try:
        return os.sched_getaffinity(tid)
    except OSError:  # the thread has ended meanwhile
        return None


def _set_affinities(plan: dict[int, set[int]]) -> None:
    for tid, cpus in plan.items():
        try:
            os.sched_setaffinity(tid, cpus)
        except OSError:  # the thread has ended meanwhile
            pass


# Environment variables read as OpenCV and numpy load (and inherited by spawned parts): their values here.
NATIVE_SETTINGS = {"OPENCV_FOR_THREADS_NUM": "1", "NUMPY_MADVISE_HUGEPAGE": "0"}


def settle_native_libraries(environ: MutableMapping[str, str] = os.environ) -> dict[str, str]:
    """Set NATIVE_SETTINGS where ``environ`` has no value of its own; the settings made.

    Where OpenCV or numpy is already loaded in this process, it is told directly as well.
    """
    made = {name: value for name, value in NATIVE_SETTINGS.items() if name not in environ}
    environ.update(made)
    if environ is not os.environ:
        return made
    if "OPENCV_FOR_THREADS_NUM" in made and "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(1)
    if "NUMPY_MADVISE_HUGEPAGE" in made and "numpy" in sys.modules:
        numpy = sys.modules["numpy"]
        core = getattr(numpy, "_core", None) or numpy.core  # numpy 2 / numpy 1
        set_hugepage = getattr(core.multiarray, "_set_madvise_hugepage", None)  # numpy's switch behind the variable
        if set_hugepage is not None:
            set_hugepage(False)
    return made


def _affinity() -> set[int]:
    try:
        return set(os.sched_getaffinity(0)) or {0}
    except (AttributeError, OSError):  # no affinity masks on this system (macOS, Windows)
        return set(range(os.cpu_count() or 1))
