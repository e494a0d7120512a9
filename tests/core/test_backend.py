"""Execution backends: local and Ray give the same run; lost workers are retried; nothing hangs.

Worker processes import this module for its tasks, so its top imports stay
light (torch and the run modules are imported inside the tests that use them).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from crchfl_sumo.core.backend import INSTALL_HINT, BackendConfig, Executor, import_ray
from crchfl_sumo.core.config import from_mapping
from crchfl_sumo.core.errors import CrchflError

TESTS = str(Path(__file__).parent)  # the Ray workers import this module's tasks


# ------------------------------------------------------------------ tasks (importable by worker processes)


def square(x: int) -> int:
    return x * x


def die_once(marker: str) -> str:
    """Kill the worker process on the first call (the marker file records it); answer on the next."""
    if not os.path.exists(marker):
        Path(marker).touch()
        os._exit(1)
    return f"pid {os.getpid()}"


def die_always() -> None:
    os._exit(1)


def sleep_s(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def user_error() -> None:
    raise CrchflError("dataset: no such folder; check the path")


def touch_or_fail(path: str) -> str:
    """Create ``path``; an empty path is a user error."""
    if not path:
        raise CrchflError("dataset: no such folder; check the path")
    Path(path).touch()
    return path


def tensor_sum(t) -> float:
    return float(t.sum())


# ------------------------------------------------------------------ settings and the local backend


def test_backend_config_rejects_bad_values():
    with pytest.raises(CrchflError, match="backend.kind"):
        BackendConfig(kind="dask")
    with pytest.raises(CrchflError, match="backend.address"):
        BackendConfig(address="auto")  # only Ray joins clusters
    with pytest.raises(CrchflError, match="max_retries"):
        BackendConfig(max_retries=-1)
    with pytest.raises(CrchflError, match="task_timeout_s"):
        BackendConfig(task_timeout_s=0)
    from crchfl_sumo.federation.run_config import RunConfig

    with pytest.raises(CrchflError, match="unknown key"):
        from_mapping(RunConfig, {"backend": {"kind": "ray", "adress": "auto"}})


def test_run_config_backend_table_and_command_line_override(tmp_path):
    from crchfl_sumo.federation.run_config import RunConfig, with_backend

    config = from_mapping(RunConfig, {"backend": {"kind": "ray", "address": "auto", "max_retries": 5}})
    assert (config.backend.kind, config.backend.address, config.backend.max_retries) == ("ray", "auto", 5)
    local = with_backend(config, "local", None)
    assert local.backend.kind == "local" and local.backend.max_retries == 5
    with pytest.raises(CrchflError, match="--backend ray"):
        with_backend(from_mapping(RunConfig, {}), None, "auto")
    assert with_backend(from_mapping(RunConfig, {}), "ray", "host:6379").backend.address == "host:6379"
    with pytest.raises(CrchflError, match="vmap"):
        from_mapping(RunConfig, {"backend": {"kind": "ray"}, "train": {"multi_vehicle": "vmap"}})


def test_missing_ray_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` fail as if it were not installed
    with pytest.raises(CrchflError) as info:
        import_ray()
    assert str(info.value) == INSTALL_HINT and "pip install 'crchfl-sumo[ray]'" in INSTALL_HINT
    with pytest.raises(CrchflError, match="crchfl-sumo\\[ray\\]"):
        with Executor(BackendConfig(kind="ray")):
            pass


def test_local_map_keeps_order_and_put_is_the_object():
    import torch

    with Executor(BackendConfig()) as executor:
        t = torch.arange(4.0)
        assert executor.put(t) is t
        assert executor.map(square, [(i,) for i in range(5)]) == [0, 1, 4, 9, 16]
        assert executor.map(tensor_sum, [(executor.put(t),)]) == [6.0]
        assert executor.map(square, []) == []


def test_local_imap_runs_each_call_when_its_result_is_asked_for():
    calls = []

    def square_noting(x):
        calls.append(x)
        return x * x

    with Executor(BackendConfig()) as executor:
        results = executor.imap(square_noting, [(1,), (2,), (3,)])
        assert calls == []
        assert next(results) == 1 and calls == [1]
        assert list(results) == [4, 9] and calls == [1, 2, 3]


def test_local_isolated_tasks_run_in_other_processes_and_a_dead_one_is_retried(tmp_path):
    with Executor(BackendConfig(num_cpus=2)) as executor:
        results = executor.map(die_once, [(str(tmp_path / "a"),), (str(tmp_path / "b"),)], isolate=True)
    assert len(results) == 2 and all(r.startswith("pid ") and r != f"pid {os.getpid()}" for r in results)
    with Executor(BackendConfig(num_cpus=1, max_retries=1)) as executor:
        with pytest.raises(CrchflError, match="died 2 times.*max_retries = 1"):
            executor.map(die_always, [()], isolate=True)


def test_on_result_reports_every_call_once_as_it_finishes():
    for isolate in (False, True):
        seen = []
        with Executor(BackendConfig(num_cpus=2)) as executor:
            results = executor.map(square, [(i,) for i in range(5)], isolate=isolate,
                                   on_result=lambda i, r: seen.append((i, r)))
        assert results == [0, 1, 4, 9, 16]
        assert sorted(seen) == [(i, i * i) for i in range(5)]
        if not isolate:
            assert seen == sorted(seen)  # in this process: in order


def test_an_isolated_call_that_raises_cancels_the_calls_not_yet_started(tmp_path):
    paths = [str(tmp_path / f"t{i}") for i in range(6)]
    with Executor(BackendConfig(num_cpus=1)) as executor:
        with pytest.raises(CrchflError, match="no such folder"):
            executor.map(touch_or_fail, [("",), *[(p,) for p in paths]], isolate=True)
    # one worker: at most the call or two already handed to the pool ran, not all six queued
    assert sum(Path(p).exists() for p in paths) <= 2


# ------------------------------------------------------------------ Ray


@pytest.fixture(scope="module")
def ray_runtime():
    ray = pytest.importorskip("ray")
    before = os.environ.get("PYTHONPATH")
    # the workers import this module's tasks
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (TESTS, before) if p)
    try:
        ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    finally:
        if before is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = before
    yield ray
    ray.shutdown()


def test_ray_map_keeps_order_and_resolves_put_objects(ray_runtime):
    import torch

    with Executor(BackendConfig(kind="ray")) as executor:
        assert executor.is_ray
        seen = []
        assert executor.map(square, [(i,) for i in range(6)], on_result=lambda i, r: seen.append((i, r))) == [
            0, 1, 4, 9, 16, 25]
        assert sorted(seen) == [(i, i * i) for i in range(6)]
        handle = executor.put(torch.arange(5.0))
        assert executor.map(tensor_sum, [(handle,), (handle,)]) == [10.0, 10.0]
    assert ray_runtime.is_initialized()  # a runtime the executor did not start is left running


def test_ray_imap_yields_in_order_and_closing_it_cancels_the_rest(ray_runtime):
    with Executor(BackendConfig(kind="ray")) as executor:
        # the first task finishes last: the others wait in order behind it
        assert list(executor.imap(sleep_s, [(1.0,), (0.0,), (0.1,)])) == [1.0, 0.0, 0.1]
        results = executor.imap(sleep_s, [(0.0,), (600.0,), (600.0,)])
        assert next(results) == 0.0
        results.close()  # the two long tasks hold both CPUs until they are cancelled
    with Executor(BackendConfig(kind="ray", task_timeout_s=120.0)) as executor:
        assert executor.map(square, [(3,)]) == [9]
        with pytest.raises(CrchflError, match="^dataset: no such folder; check the path$"):
            list(executor.imap(user_error, [()]))


def test_ray_worker_that_dies_is_retried(ray_runtime, tmp_path):
    with Executor(BackendConfig(kind="ray", max_retries=2)) as executor:
        assert executor.map(die_once, [(str(tmp_path / "marker"),)])[0].startswith("pid ")
    with Executor(BackendConfig(kind="ray", max_retries=0)) as executor:
        with pytest.raises(CrchflError, match="max_retries = 0"):
            executor.map(die_always, [()])


def test_ray_task_that_never_finishes_times_out_instead_of_hanging(ray_runtime):
    with Executor(BackendConfig(kind="ray", task_timeout_s=1.0)) as executor:
        with pytest.raises(CrchflError, match="task_timeout_s = 1 s"):
            executor.map(sleep_s, [(60.0,)])
    with Executor(BackendConfig(kind="ray")) as executor:
        assert executor.map(square, [(3,)]) == [9]  # the runtime still works


def test_ray_task_user_error_arrives_as_crchfl_error(ray_runtime):
    with Executor(BackendConfig(kind="ray")) as executor:
        with pytest.raises(CrchflError, match="^dataset: no such folder; check the path$"):
            executor.map(user_error, [()])


def test_same_seed_same_run_on_local_and_ray(ray_runtime, tmp_path):
    import torch

    from crchfl_sumo.federation.run import run_federation_dir
    from crchfl_sumo.federation.run_config import RunConfig
    from crchfl_sumo.federation.run_data import read_inputs
    from crchfl_sumo.learning.checkpoint import load_checkpoint

    from helpers import PAPER_VEHICLES, result_files, run_config, write_dataset

    data = write_dataset(tmp_path / "data", PAPER_VEHICLES, samples=(5, 3, 4, 2, 3))
    mapping = run_config(data, scheme="crchfl", pretrain_batch=4, pretrain_epochs=1, cloud_interval=2, cloud_rounds=1)
    mapping["federation"]["evaluate_every_edge"] = True
    local = from_mapping(RunConfig, mapping)
    ray = from_mapping(RunConfig, {**mapping, "backend": {"kind": "ray"}})
    a = run_federation_dir(local, read_inputs(local), tmp_path / "local")
    b = run_federation_dir(ray, read_inputs(ray), tmp_path / "ray")
    assert a == b
    assert result_files(tmp_path / "local") == result_files(tmp_path / "ray")
    wa = load_checkpoint(tmp_path / "local" / "final_model.pt").state_dict
    wb = load_checkpoint(tmp_path / "ray" / "final_model.pt").state_dict
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    # a run started on one backend resumes on the other: the backend is not part of the run's settings
    assert (tmp_path / "local" / "config.json").read_text() == (tmp_path / "ray" / "config.json").read_text()


def test_sweep_runs_on_ray_give_the_local_rows(ray_runtime, tmp_path):
    from crchfl_sumo.studies.sweep import parse_param, run_sweep

    from helpers import PAPER_VEHICLES, run_config, write_dataset

    data = write_dataset(tmp_path / "data", PAPER_VEHICLES)
    base = run_config(data, scheme="hfl", cloud_rounds=1)
    params = [parse_param("federation.edge_interval=1,2")]
    local = run_sweep(base, params, tmp_path / "local", BackendConfig(num_cpus=2))
    remote = run_sweep(base, params, tmp_path / "ray", BackendConfig(kind="ray"))
    assert local == remote and [r["cloud_rounds"] for r in remote] == [1, 1]
