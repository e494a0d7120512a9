"""CPU counts from the affinity mask, /proc/stat arithmetic, and when waiting threads are told to sleep."""

import os
import sys
import time

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


@pytest.fixture
def no_pinning(torch_not_loaded, monkeypatch):
    monkeypatch.setattr(cpus, "can_pin_threads", lambda: False)


def test_unpinnable_waiting_threads_sleep_when_other_processes_keep_a_cpu_busy(no_pinning):
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=1.0) == "PASSIVE"
    assert environ == {"OMP_WAIT_POLICY": "PASSIVE"}


def test_waiting_threads_keep_spinning_on_an_idle_machine(no_pinning):
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=0.2) is None
    assert environ == {}


def test_pinned_threads_keep_spinning_beside_busy_processes(torch_not_loaded, monkeypatch):
    monkeypatch.setattr(cpus, "can_pin_threads", lambda: True)
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=1.0) is None  # one part on both CPUs: pinned
    assert environ == {}
    assert cpus.choose_wait_policy(environ, busy=1.0, parts=2) is None  # a thread a part: nothing waits


def test_parts_sharing_the_cpus_with_several_threads_each_sleep_when_busy(torch_not_loaded, monkeypatch):
    monkeypatch.setattr(cpus, "can_pin_threads", lambda: True)
    monkeypatch.setattr(cpus, "available_cpus", lambda: 4)
    environ = {}
    assert cpus.choose_wait_policy(environ, busy=1.0, parts=2) == "PASSIVE"  # 2 threads a part, not pinned
    assert environ == {"OMP_WAIT_POLICY": "PASSIVE"}


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


def test_pin_plan_puts_the_main_thread_first_and_the_others_in_turn_on_the_rest():
    assert cpus.pin_plan(10, [30, 20], [4, 7]) == {10: {4}, 20: {7}, 30: {7}}
    # Three CPUs: any two threads in a row of id (OpenMP's workers) land on different ones.
    plan = cpus.pin_plan(1, [5, 2, 3, 4], [0, 1, 2])
    assert plan == {1: {0}, 2: {1}, 3: {2}, 4: {1}, 5: {2}}


@pytest.mark.skipif(not cpus.can_pin_threads() or cpus.available_cpus() < 2, reason="needs 2 CPUs and affinity calls")
def test_pinned_threads_pins_while_inside_and_gives_every_thread_its_cpus_back():
    import threading

    import torch

    mask = os.sched_getaffinity(0)
    before = torch.get_num_threads()
    torch.set_num_threads(len(mask))
    started: list[int] = []
    try:
        with cpus.pinned_threads() as pinned:
            assert pinned
            assert os.sched_getaffinity(0) == {min(mask)}  # the main thread on the first CPU
            python = {t.native_id for t in threading.enumerate()}
            native = [int(t) for t in os.listdir(cpus.TASKS_PATH) if int(t) not in python]
            assert native  # OpenMP's workers, started for the pinning
            assert all(len(os.sched_getaffinity(t)) == 1 and os.sched_getaffinity(t) != {min(mask)} for t in native)
            with cpus.pinned_threads() as inner:
                assert not inner  # already pinned
            thread = threading.Thread(target=lambda: started.append(threading.get_native_id()) or time.sleep(0.5))
            thread.start()  # inherits the pinned main thread's CPU
            while not started:
                time.sleep(0.01)
        assert os.sched_getaffinity(0) == mask
        assert all(os.sched_getaffinity(t) == mask for t in native)
        assert os.sched_getaffinity(started[0]) == mask  # a thread started inside gets the main thread's CPUs
        thread.join()
        torch.set_num_threads(1)
        with cpus.pinned_threads() as pinned:
            assert not pinned and os.sched_getaffinity(0) == mask  # one thread: nothing to pin
    finally:
        torch.set_num_threads(before)
