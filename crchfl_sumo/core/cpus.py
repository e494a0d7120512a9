"""The CPUs this process may use, and how torch's OpenMP threads wait for work.

Thread counts follow the affinity mask (``os.sched_getaffinity``: what a
container, ``taskset`` or a batch scheduler grants), divided among the parts
that run side by side. They never follow the momentary load: a different
number of threads sums floating-point reductions in a different order, and
the same config and seed must give the same metrics.

How waiting threads wait does not change a result, only its speed, so that one
does follow the load. By default OpenMP threads spin for a while after each
parallel region; on a machine whose cores are busy with other processes the
spinning threads take the cores from the threads with work, and two threads
were measured far slower than one (docs/benchmarks.md). When other processes
keep at least ``BUSY_CPUS`` CPUs busy as a command starts, waiting threads
sleep instead (``OMP_WAIT_POLICY=PASSIVE``). On an idle machine spinning is
kept: sleeping threads made training a third slower there.

Two defaults of native libraries cost this workload more than they give, so
every command turns them off where the user has not set them
(``settle_native_libraries``; docs/benchmarks.md): OpenCV's worker threads,
which split each 64 x 128 image operation and spend their time waking and
waiting, and numpy's MADV_HUGEPAGE on large arrays, whose first touch stalls
in the kernel's memory compaction where transparent hugepages are 'madvise'
(numpy issue 31590). Neither changes a result.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from typing import MutableMapping

log = logging.getLogger(__name__)

BUSY_CPUS = 0.5  # CPUs kept busy by other processes from which waiting threads sleep
SAMPLE_S = 0.1  # how long the start of a command watches the CPUs
WAIT_POLICY = "OMP_WAIT_POLICY"
STAT_PATH = "/proc/stat"


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


def choose_wait_policy(environ: MutableMapping[str, str] = os.environ, busy: float | None = None) -> str | None:
    """Let torch's waiting threads sleep when other processes keep the CPUs busy: the policy set, or None.

    Acts only before torch is imported (OpenMP reads the policy once, when it
    loads) and only where the user has set no policy or thread count of their own.
    ``busy`` (CPUs) is measured when not given.
    """
    if "torch" in sys.modules or WAIT_POLICY in environ or "OMP_NUM_THREADS" in environ:
        return None
    if available_cpus() < 2:
        return None  # one thread: nothing waits
    if busy is None:
        busy = busy_cpus()
    if busy is None or busy < BUSY_CPUS:
        return None
    environ[WAIT_POLICY] = "PASSIVE"
    log.info("%.1f of %d CPUs busy with other processes: torch's waiting threads sleep", busy, available_cpus())
    return "PASSIVE"


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
