"""`yauyau precompute` on Dask (solver/offline/distributed.py): a real `dask scheduler` and two `dask worker`
processes on localhost, against a run in one process.

Truth: the arrays of the one-process run; the file made on the cluster must hold the same arrays bit
for bit (the column blocks are fixed, so it does not matter which worker solved which), also when a
worker is killed (SIGKILL) while it solves: the scheduler runs its tasks again on the other one.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.cluster import SPEC, Cluster
from yauyau.service.cli import main
from yauyau.solver import spec_from_dict
from yauyau.storage.model_store import ModelStore

import yauyau


@pytest.fixture
def cluster(tmp_path):
    running = Cluster(tmp_path, 2)
    yield running
    running.close()


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The arrays solved in this process (no cluster)."""
    store = ModelStore(tmp_path_factory.mktemp("local"))
    return store.load(yauyau.precompute(spec_from_dict(SPEC), store, workers=1)).arrays


def _same_arrays(path: Path, model_id: str, expected: dict) -> None:
    arrays = ModelStore(path).load(model_id).arrays
    assert set(arrays) == set(expected)
    for name, value in expected.items():
        assert arrays[name].dtype == value.dtype and np.array_equal(arrays[name], value), name


@pytest.mark.slow
def test_the_cli_on_a_running_cluster_writes_the_same_arrays(cluster, local, tmp_path, capsys):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(spec_from_dict(SPEC).canonical_json())
    code = main(["precompute", str(spec_file), "--store", str(tmp_path / "store"),
                 "--scheduler", cluster.address])
    assert code == 0
    model_id = capsys.readouterr().out.strip().splitlines()[-1]
    _same_arrays(tmp_path / "store", model_id, local)
    attrs = ModelStore(tmp_path / "store").load(model_id).attrs
    assert attrs["scheduler"] == cluster.address and "workers" not in attrs  # not the unused --workers


@pytest.mark.slow
def test_a_worker_killed_during_the_solves_changes_nothing(cluster, local, tmp_path):
    killed = []

    def progress(done: int, size: int) -> None:
        if not killed:  # the first block is in: the other worker is busy with its own
            os.kill(cluster.workers[0].pid, signal.SIGKILL)
            killed.append(done)

    model_id = yauyau.precompute(spec_from_dict(SPEC), tmp_path / "store", scheduler=cluster.address,
                                 progress=progress)
    assert killed and killed[0] < SPEC["discretization"]["basis"]
    assert cluster.workers[0].wait(timeout=10) == -signal.SIGKILL
    _same_arrays(tmp_path / "store", model_id, local)


@pytest.mark.slow
def test_a_block_whose_future_is_cancelled_is_solved_again(cluster, local, tmp_path):
    """What a worker's death can also do: the scheduler gives up a block's key instead of computing it
    again (seen once in CI).  Here one pending block is cancelled outright from the progress callback;
    the block is submitted again under a new key and the arrays are still those of one process."""
    from distributed import Future, default_client

    cancelled = []

    def progress(done: int, size: int) -> None:
        if cancelled:
            return
        client = default_client()  # the run's own client
        waiting = [key for key, state in client.futures.items()
                   if str(key).startswith("yauyau-propagators-") and state.status == "pending"]
        if waiting:
            client.cancel([Future(waiting[-1], client)])
            cancelled.append(waiting[-1])

    model_id = yauyau.precompute(spec_from_dict(SPEC), tmp_path / "store", scheduler=cluster.address,
                                 progress=progress)
    assert cancelled
    _same_arrays(tmp_path / "store", model_id, local)


@pytest.mark.slow
def test_a_local_cluster_of_two_workers_writes_the_same_arrays(local, tmp_path):
    model_id = yauyau.precompute(spec_from_dict(SPEC), tmp_path / "store", workers=2)
    _same_arrays(tmp_path / "store", model_id, local)


def test_an_unreachable_scheduler_is_a_clear_error(tmp_path, capsys):
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(spec_from_dict(SPEC).canonical_json())
    assert main(["precompute", str(spec_file), "--store", str(tmp_path / "s"),
                 "--scheduler", "localhost:1"]) == 2
    assert "--scheduler" in capsys.readouterr().err
    # a well-formed address where nothing listens: refused by the probe, not after the Client's 30 s
    assert main(["precompute", str(spec_file), "--store", str(tmp_path / "s"),
                 "--scheduler", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler tcp://127.0.0.1:1: nothing answers at 127.0.0.1:1" in err
    assert "Traceback" not in err and not ModelStore(tmp_path / "s").ids()


ATLAS = {"name": "sin drift atlas", "state": ["x"], "drift": ["0.8 + 0.3*sin(x)"], "observation": ["x"],
         "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
         "domain": {"radius": 6.0, "follow": True, "region": [[-5.0, 60.0]]},
         "discretization": {"dt": 0.02, "basis": 48}}


def _every_row(path: Path, model_id: str) -> tuple[dict, dict]:
    stored = ModelStore(path).load(model_id)
    rows = {name: np.stack([stored.lazy.read(name, k) for k in range(stored.lazy.shape(name)[0])])
            for name in stored.lazy.names}
    return stored.arrays, rows


@pytest.mark.slow
def test_an_atlas_on_a_running_cluster_is_the_same_file_also_with_a_worker_killed(cluster, tmp_path):
    """The atlas's solves (69 centres x 2 column blocks) as tasks on the cluster; one worker dies."""
    local_id = yauyau.precompute(spec_from_dict(ATLAS), tmp_path / "local", workers=1)
    killed = []

    def progress(done: int, size: int) -> None:
        if done > ATLAS["discretization"]["basis"] and not killed:  # the atlas's first block is in
            os.kill(cluster.workers[0].pid, signal.SIGKILL)
            killed.append(done)

    model_id = yauyau.precompute(spec_from_dict(ATLAS), tmp_path / "cluster", scheduler=cluster.address,
                                 progress=progress)
    assert model_id == local_id and killed and killed[0] < 69 * 48
    assert cluster.workers[0].wait(timeout=10) == -signal.SIGKILL
    arrays, rows = _every_row(tmp_path / "cluster", model_id)
    want_arrays, want_rows = _every_row(tmp_path / "local", local_id)
    assert set(rows) == {"atlas_propagator_fp", "atlas_generator"} and rows["atlas_generator"].shape[0] == 69
    for got, want in ((arrays, want_arrays), (rows, want_rows)):
        assert set(got) == set(want)
        for name, value in want.items():
            assert np.array_equal(got[name], value), name


@pytest.mark.slow
def test_a_script_without_the_main_guard_is_told_why_its_local_workers_did_not_start(tmp_path):
    """Local workers import the calling script again (spawn): without ``if __name__ == "__main__":`` they
    cannot start.  The error names ``workers`` and the fix, not an unreachable scheduler "None"."""
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from yauyau.solver import compile_model, spec_from_dict\n"
        "from yauyau.solver.errors import InputError\n"
        "from yauyau.solver.offline.pipeline import precompute\n"
        f"spec = {dict(SPEC, discretization={'dt': 0.02, 'basis': 100})!r}\n"  # 4 column blocks: a cluster
        "try:\n"
        "    precompute(compile_model(spec_from_dict(spec)), workers=2)\n"
        "except InputError as exc:\n"
        "    print('FIELD', exc.field)\n"
        "    print('MESSAGE', exc)\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path).stdout
    assert "FIELD workers" in out, out
    assert 'if __name__ == "__main__"' in out and "scheduler None" not in out
