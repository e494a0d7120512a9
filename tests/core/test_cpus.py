"""CPU counts from the affinity mask, /proc/stat arithmetic, and when waiting threads are told to sleep."""

import os
import sys

import pytest

from crchfl_sumo.core import cpus

# Two CPUs of a /proc/stat: user nice system idle iowait irq softirq steal guest guest_nice.
STAT = """cpu  300 0 100 900 50 0 0 0 0 0
cpu0 100 0 50 400 10 0 0 0 0 0
cpu1 200 0 50 500 40 0 0 0 0 0
intr 12345 0 0
ctxt 999
"""


def test_cpu_times_sums_the_chosen_cpus_and_leaves_idle_and_iowait_out():
    # cpu0: total 560, busy 560 - 400 - 10 = 150; cpu1: total 790, busy 790 - 500 - 40 = 250.
    assert cpus.cpu_times(STAT, {0}) == (150, 560)
    assert cpus.cpu_times(STAT, {1}) == (250, 790)
    assert cpus.cpu_times(STAT, {0, 1}) == (400, 1350)  # the aggregate "cpu" line is not counted again
    assert cpus.cpu_times(STAT, {5}) == (0, 0)


def test_busy_cpus_is_the_busy_share_of_the_ticks_times_the_cpus(tmp_path, monkeypatch):
    texts = iter([STAT, STAT.replace("cpu0 100 0 50 400", "cpu0 150 0 50 450").replace("cpu1 200 0 50 500", "cpu1 300 0 50 500")])
    path = tmp_path / "stat"

    def fake_sleep(seconds):
        path.write_text(next(texts))

    monkeypatch.setattr(cpus, "_affinity", lambda: {0, 1})
    monkeypatch.setattr(cpus, "STAT_PATH", str(path))
    monkeypatch.setattr(cpus.time, "sleep", fake_sleep)
    path.write_text(next(texts))
    # Between the reads: busy +50 (cpu0) +100 (cpu1), total +100 +100: 2 CPUs x 150 / 200 = 1.5 busy.
    assert cpus.busy_cpus() == pytest.approx(1.5)


def test_busy_cpus_is_none_without_a_stat_file(tmp_path, monkeypatch):
    monkeypatch.setattr(cpus, "STAT_PATH", str(tmp_path / "missing"))
    assert cpus.busy_cpus(sample_s=0) is None


def test_thread_counts_follow_the_affinity_mask_and_the_parts(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2, 5, 7}, raising=False)
    assert cpus.available_cpus() == 4
    assert cpus.threads_per_part(1) == 4
    assert cpus.threads_per_part(2) == 2
    assert cpus.threads_per_part(3) == 1  # 4 // 3
    assert cpus.threads_per_part(8) == 1  # never fewer than one


@pytest.fixture
def torch_not_loaded(monkeypatch):
    """The policy can only be chosen before torch loads; the test process has it loaded."""
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    monkeypatch.setattr(cpus, "available_cpus", lambda: 2)


def test_waiting_threads_sleep_when_other_processes_keep_a_cpu_busy(torch_not_loaded):
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=1.0) == "PASSIVE"
    assert environ == {"OMP_WAIT_POLICY": "PASSIVE"}


def test_waiting_threads_keep_spinning_on_an_idle_machine(torch_not_loaded):
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=0.2) is None
    assert environ == {}


@pytest.mark.parametrize("setting", [{"OMP_WAIT_POLICY": "ACTIVE"}, {"OMP_NUM_THREADS": "2"}])
def test_the_users_own_thread_settings_are_kept(torch_not_loaded, setting):
    environ = dict(setting)
    assert cpus.choose_wait_policy(environ, busy=2.0) is None
    assert environ == setting


def test_nothing_is_set_once_torch_is_loaded(monkeypatch):
    import torch  # noqa: F401  (loaded: OpenMP has read its settings)

    environ = {}
    assert cpus.choose_wait_policy(environ, busy=2.0) is None
    assert environ == {}


def test_one_cpu_has_no_waiting_threads(monkeypatch):
    monkeypatch.delitem(sys.modules, "torch", raising=False)
    monkeypatch.setattr(cpus, "available_cpus", lambda: 1)
    assert cpus.choose_wait_policy({}, busy=2.0) is None


def test_native_settings_are_made_only_where_the_user_set_none():
    environ = {"OPENCV_FOR_THREADS_NUM": "2"}
    assert cpus.settle_native_libraries(environ) == {"NUMPY_MADVISE_HUGEPAGE": "0"}
    assert environ == {"OPENCV_FOR_THREADS_NUM": "2", "NUMPY_MADVISE_HUGEPAGE": "0"}
    assert cpus.settle_native_libraries(environ) == {}


@pytest.mark.parametrize("user_threads, threads, hugepages", [(None, 1, False), ("2", 2, False)])
def test_native_libraries_already_loaded_are_told_directly(user_threads, threads, hugepages):
    """In a fresh process (the settings are process-wide): numpy and OpenCV load first, as the CLI loads them."""
    import os
    import subprocess

    code = (
        "import cv2, numpy\n"
        "from crchfl_sumo.core.cpus import settle_native_libraries\n"
        "settle_native_libraries()\n"
        "print(cv2.getNumThreads(), numpy._core.multiarray._get_madvise_hugepage())\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in cpus.NATIVE_SETTINGS}
    if user_threads is not None:
        env["OPENCV_FOR_THREADS_NUM"] = user_threads
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == [str(threads), str(hugepages)]
