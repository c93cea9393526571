"""The offline stage's independent solves as Dask tasks (``yauyau precompute --workers K`` or
``--scheduler tcp://HOST:PORT``).

The propagators e^{dt L}φ_k, e^{dt L_K}φ_k of seed 002 §5 are N independent solves; they run in
fixed blocks of basis columns (solver/offline/pipeline.py ``column_blocks``), one Dask task per block.  The
job (the two sparse operators, the weights, the basis values) is scattered to every worker once;
each worker factors the two matrices once per job and solves the blocks it is given.  A block's
result depends only on the job and the block, so the arrays are bit-identical whatever the cluster
(one process, a local cluster of any size, machines on a network) and whichever worker solved which
block.  A worker that dies takes its running tasks with it: the scheduler runs them again elsewhere
(up to its ``allowed-failures``), and the answer is the same.  Where the scheduler gives a block up
instead (its future cancelled), the block is submitted again under a new key (RESUBMITS times).

A cluster that loses every worker (all killed, and none back within :data:`WORKERLESS_S` seconds), or
its scheduler, ends the run with one InputError naming the scheduler and what to do (the CLI prints
one line, exit status 2); nothing is stored.

Without ``scheduler`` a local cluster of ``workers`` processes (one thread each: SuperLU's solves do
not gain from threads, bench/results/precompute.md) is started for the run and shut down after it; they
are spawned, so a script asking for several needs the usual ``if __name__ == "__main__":`` guard.
Workers of a cluster of your own should run one thread each too (``dask worker --nthreads 1``); a
worker with more threads solves its blocks one at a time (a lock: the factorisations are shared).
"""

from __future__ import annotations

import dataclasses
import socket
import threading
from collections.abc import Iterator
from concurrent.futures import CancelledError
from contextlib import contextmanager
from typing import Any, Callable

from ..errors import InputError

_LOCK = threading.Lock()
CONNECT_TIMEOUT = "30s"
PROBE_TIMEOUT = 5.0  # seconds a TCP connection to the scheduler may take (checked before the Client)
RESUBMITS = 3  # times a block whose future was cancelled (its worker died) is submitted again
WORKERLESS_S = 30.0  # seconds a cluster may have no worker at all before the run gives up


def solve_block(solve: Callable[[Any, tuple[int, int]], Any], job: Any, columns: tuple[int, int],
                basis: Any = None):
    """The task: ``solve(job, columns)``, one block of columns on this worker (serialised per process,
    see the docstring); ``basis``: the initial values when the job was sent without them."""
    if basis is not None:
        job = dataclasses.replace(job, initial=basis)
    with _LOCK:
        return solve(job, columns)


def _check_reachable(scheduler: str) -> None:
    """Refuse at once a tcp:// address where nothing listens (Dask's Client retries a refused
    connection until its 30 s timeout); a scheduler that answers slowly still gets the timeout."""
    from urllib.parse import urlsplit

    if not scheduler.startswith("tcp://"):
        return
    try:
        parts = urlsplit(scheduler)
        host, port = parts.hostname, parts.port or 8786
    except ValueError as exc:
        raise InputError("scheduler", f"{scheduler!r} is not a Dask scheduler address ({exc}): give "
                                      "tcp://HOST:PORT") from None
    try:
        socket.create_connection((host, port), timeout=PROBE_TIMEOUT).close()
    except OSError as exc:
        raise InputError("scheduler", f"cannot reach the Dask scheduler {scheduler}: nothing answers at "
                                      f"{host}:{port} ({exc.strerror or exc}); start one with `dask "
                                      "scheduler` or check the address") from None


@contextmanager
def dask_client(workers: int = 1, scheduler: str | None = None) -> Iterator[Any]:
    """A Dask client: on a local cluster of ``workers`` processes (one thread each) started for the block
    and shut down after it, or connected to the running ``scheduler``; InputError naming ``workers`` or
    ``scheduler`` when neither can be had.  ``yauyau precompute`` and ``yauyau fit --workers`` use it."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:  # pragma: no cover - distributed is a dependency
        raise InputError("scheduler", "Dask distributed is not installed (pip install distributed)") from None
    cluster = None
    try:
        if scheduler is None:
            # Dask's own start method (spawn): a fork of this process, which may run threads of its
            # own (a server, a thread pool), can deadlock in the child.  Spawned workers import the
            # caller's main module again, so a script needs its `if __name__ == "__main__":` guard.
            try:
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=40)
            except RuntimeError as exc:
                raise InputError("workers", f"cannot start {workers} local Dask workers ({exc}); a script "
                                            "that asks for workers > 1 must call it under "
                                            'if __name__ == "__main__": (the workers import the script '
                                            "again), or use workers = 1") from None
            client = Client(cluster)
        else:
            _check_reachable(scheduler)
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
    except InputError:  # the local cluster's own message (an InputError is a ValueError too)
        raise
    except (OSError, TimeoutError, ValueError) as exc:
        if cluster is not None:
            cluster.close()
        raise InputError("scheduler", f"cannot reach the Dask scheduler {scheduler}: {exc}") from None
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_blocks(jobs: list[Any], tasks: list[tuple[int, tuple[int, int]]],
               store: Callable[[int, Any], None], solve: Callable[[Any, tuple[int, int]], Any], *,
               workers: int = 1, scheduler: str | None = None) -> None:
    """Solve ``tasks`` ((job index, column block) pairs) on Dask with ``solve(job, block)`` (a module-level
    function: workers import it by name), calling ``store(j, result)`` as each block arrives.  Every job
    is scattered to every worker once."""
    with dask_client(workers, scheduler) as client:
        watch = _Watch(client, WORKERLESS_S)
        try:
            _solve(client, jobs, tasks, store, solve, watch)
        except InputError:
            raise
        except (TimeoutError, OSError, CancelledError, _killed_worker()) as exc:  # the cluster, not the spec
            raise InputError(*_lost(scheduler, workers, exc, watch)) from None
        finally:
            watch.stop()


def _solve(client, jobs: list[Any], tasks: list[tuple[int, tuple[int, int]]],
           store: Callable[[int, Any], None], solve: Callable[[Any, tuple[int, int]], Any],
           watch: "_Watch") -> None:
    from distributed import as_completed

    values = None  # an atlas's jobs share the basis values: sent once, not once per centre
    if len(jobs) > 1 and all(job.initial is jobs[0].initial for job in jobs):
        values = jobs[0].initial
        jobs = [dataclasses.replace(job, initial=None) for job in jobs]
    basis = None if values is None else client.scatter(values, broadcast=True, hash=False)
    shared = [client.scatter(job, broadcast=True, hash=False) for job in jobs]

    def submit(j: int, block: tuple[int, int], attempt: int):
        nonlocal basis
        if attempt:  # the scattered data may be what was lost (a cancel "for lost dependencies")
            if basis is not None and basis.status != "finished":
                basis = client.scatter(values, broadcast=True, hash=False)
            if shared[j].status != "finished":
                shared[j] = client.scatter(jobs[j], broadcast=True, hash=False)
        key = f"yauyau-propagators-{jobs[j].token}-{block[0]}" + (f"-again{attempt}" if attempt else "")
        return client.submit(solve_block, solve, shared[j], block, basis, retries=2, pure=False, key=key)

    futures = {submit(j, block, 0): (j, block, 0) for j, block in tasks}
    watch.futures = futures  # the same dict, kept up to date below: what the watch cancels
    pending = as_completed(list(futures))
    for future in pending:
        j, block, attempt = futures.pop(future)
        try:
            result = future.result()
        except CancelledError:
            # a worker died holding this block's finished result, or the only copy of the job's
            # scattered data, and the scheduler gave the key up instead of recomputing it (the
            # killed-worker tests, about one run in two): the block is deterministic, so it is
            # solved again under a new key, with the lost data scattered again
            if attempt >= RESUBMITS or watch.gave_up:
                raise
            again = submit(j, block, attempt + 1)
            futures[again] = (j, block, attempt + 1)
            pending.add(again)
            continue
        store(j, result)
        future.release()
        watch.futures = futures


def _killed_worker() -> type[BaseException]:
    from distributed.scheduler import KilledWorker

    return KilledWorker


def _lost(scheduler: str | None, workers: int, exc: BaseException, watch: "_Watch") -> tuple[str, str]:
    """(field, message) of a run whose cluster failed: which cluster, what happened, what to do."""
    if watch.gave_up:
        what = f"had no worker for {watch.patience:g} s"
    else:
        what = f"failed ({type(exc).__name__}: {str(exc).strip() or 'no detail'})"
    if scheduler is None:
        return "workers", (f"the local Dask cluster of {workers} worker(s) {what} while solving the "
                           "propagators; nothing was stored: run precompute again (--workers 1 solves in "
                           "this process)")
    return "scheduler", (f"the Dask cluster at {scheduler} {what} while solving the propagators (its workers "
                         f"were stopped or lost); nothing was stored: start workers again (dask worker "
                         f"{scheduler} --nthreads 1) and run precompute again, or leave out --scheduler")


class _Watch:
    """Gives up on a cluster with no worker for ``patience`` seconds: cancels the run's futures (the
    result loop then ends) instead of waiting for workers that may never come back."""

    def __init__(self, client, patience: float, every: float = 1.0):
        self.client, self.patience, self.every = client, patience, every
        self.futures: dict = {}
        self.gave_up = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="yauyau-dask-watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import time

        alone_since = None
        while not self._stop.wait(self.every):
            try:
                count = len(self.client.scheduler_info().get("workers", {}))
            except Exception:  # noqa: BLE001 - a client closing under us: the loop ends anyway
                return
            now = time.monotonic()
            alone_since = None if count else (alone_since or now)
            if alone_since is not None and now - alone_since >= self.patience:
                self.gave_up = True
                try:
                    self.client.cancel(list(self.futures))
                except Exception:  # noqa: BLE001 - the scheduler may be gone too: the loop sees that
                    pass
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
