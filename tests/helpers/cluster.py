"""A real Dask cluster on localhost for the tests of `precompute --scheduler` (a scheduler and workers
as separate processes), and the spec they solve."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

DASK = str(Path(sys.executable).parent / "dask")
SPEC = {"name": "ou-2d-dask", "state": ["p", "q"], "drift": ["-p", "-0.5*q"], "observation": ["p", "q"],
        "method": "yau-yau",
        "initial": {"kind": "gaussian", "mean": [0.2, -0.2], "cov": [[0.5, 0.0], [0.0, 0.5]]},
        "domain": {"radius": 5.0}, "discretization": {"dt": 0.02, "basis": 300}}


class Cluster:
    """A scheduler and workers as separate processes (the `dask` command of this environment)."""

    def __init__(self, directory: Path, workers: int):
        self.file = directory / "scheduler.json"
        self.procs = [subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                        "--no-dashboard", "--scheduler-file", str(self.file)],
                                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
        deadline = time.monotonic() + 60
        while not self.file.exists():
            assert time.monotonic() < deadline, "the scheduler did not start"
            time.sleep(0.1)
        self.workers = [subprocess.Popen([DASK, "worker", "--scheduler-file", str(self.file), "--nthreads",
                                          "1", "--no-nanny", "--no-dashboard", "--host", "127.0.0.1"],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                        for _ in range(workers)]
        self.procs += self.workers
        from distributed import (
            Client,  # lazy: distributed takes a second to import, only cluster tests need it
        )

        with Client(scheduler_file=str(self.file), timeout="60s") as client:
            client.wait_for_workers(workers, timeout=120)
            self.address = client.scheduler.address

    def close(self):
        for proc in reversed(self.procs):
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
