"""core.background.BackgroundSaver: saves in order on one thread, errors reach the caller, the end waits."""

from __future__ import annotations

import threading
import time

import pytest

from crchfl_sumo.core.background import BackgroundSaver


def test_saves_run_in_order_on_one_other_thread_and_the_block_waits_for_the_last():
    done, threads = [], set()

    def save(k):
        time.sleep(0.01 * (3 - k))  # the first is the slowest: a pool of several would reorder them
        threads.add(threading.get_ident())
        done.append(k)

    with BackgroundSaver() as saver:
        for k in range(3):
            saver.submit(save, k)
    assert done == [0, 1, 2]
    assert threads and threading.get_ident() not in threads and len(threads) == 1


def test_a_save_runs_while_the_caller_goes_on():
    release, started = threading.Event(), threading.Event()

    def save():
        started.set()
        assert release.wait(10)

    with BackgroundSaver() as saver:
        saver.submit(save)
        assert started.wait(10)  # submit returned while the save is still blocked
        release.set()


def test_a_failed_save_is_raised_at_the_next_submit_and_nothing_after_it_runs():
    ran = []

    def fail():
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        with BackgroundSaver() as saver:
            saver.submit(fail)
            saver.submit(ran.append, 1)
    assert ran == []


def test_leaving_on_an_error_still_waits_for_the_save_in_flight_and_keeps_the_first_error():
    finished = []

    def slow():
        time.sleep(0.05)
        finished.append(True)

    with pytest.raises(KeyError):
        with BackgroundSaver() as saver:
            saver.submit(slow)
            raise KeyError("the caller's")
    assert finished == [True]  # the folder is complete when the caller sees its error

    with pytest.raises(KeyError):  # the save's own error is only logged
        with BackgroundSaver() as saver:
            saver.submit(lambda: 1 / 0)
            raise KeyError("the caller's")
