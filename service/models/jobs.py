"""Models added at run time: ``POST /v1/models`` precomputes a spec as a background job.

The job's id is the model id (the content hash of the canonical spec), so the same spec sent twice,
to any worker of any server sharing the model store, is one job and is computed once: the job is a
file ``<store>/jobs/<id>.json`` created exclusively (``O_EXCL``) by the request that starts it.  The
precompute runs in a process of its own (``python -m yauyau.service.models.jobs STORE ID``: the serving
worker stays free), which writes its progress (propagators solved / basis size) into that file,
then ``done`` once the model file is saved — it then appears in ``GET /v1/models`` — or ``failed``
with the reason.  The job's process holds an exclusive lock on ``<id>.lock`` for its lifetime (the
heartbeat alone is not enough: the eigensolve holds the GIL for minutes); a job whose lock is free
and whose file has been silent for ``STALE_S`` seconds died (its host restarted) and may be started
again by the next request.  A job is claimed under an exclusive lock on ``<id>.claim``, so of the
requests that find it missing or dead at once, one starts it.  Before any
work, a spec is checked (the spec's own rules, field by field) and refused with a 413 problem when
it is larger than the service allows (basis size, mesh nodes, atlas centres:
``YAUYAU_MAX_PRECOMPUTE_BASIS``/``_NODES``/``_CENTRES``) or than the machine's memory holds (a
yau-niu point budget, ``discretization.points``).

The jobs wait in a queue shared by every worker and host of the store (19 specs posted in a second
once started 19 processes, 2.1 GB): a new job is ``queued`` (no process), and a dispatcher, under an
exclusive lock on ``<store>/jobs/queue.lock``, starts the oldest queued jobs while fewer than
``max_jobs`` run.  It runs when a job is submitted, when a job process this worker started ends, and
when ``GET /v1/jobs/{id}`` asks about a queued job or one whose process died (its slot is reclaimed
then).  At most ``max_queued`` wait; beyond, the submission is refused (QueueFull: 503 with
Retry-After).  A queued job reports its ``position`` (1: next).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

STALE_S = 120.0  # a running job silent this long, whose lock is not held on this host, is taken as dead
_FIELDS = ("id", "status", "progress", "done", "total", "error", "name", "queued", "started", "updated",
           "pid")
QUEUE_RETRY_S = 30  # the Retry-After of a submission refused because the queue is full


class QueueFull(Exception):
    """``max_queued`` jobs already wait for a slot (503 with Retry-After)."""


class PrecomputeLimit(Exception):
    """A spec larger than the service precomputes (413): ``field`` says which size, ``message`` why."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def _atlas_centres(model: Any) -> int:
    """About how many balls an atlas ([domain] region) asks for (the lattice before its spacing is
    rounded to whole elements); 0 without one."""
    from yauyau.solver.engine.atlas import lattice, needs_atlas

    if not needs_atlas(model):
        return 0
    return lattice(model).size


def _check_point_budget(spec: Any) -> None:
    """A yau-niu point budget whose arrays would not fit in this machine's memory: PrecomputeLimit
    naming ``spec.discretization.points``, the memory it needs and the limit (before any work)."""
    from yauyau.solver.errors import TooLarge
    from yauyau.solver.qmc.budget import check_points
    from yauyau.solver.registry import AUTO, QMC_ONLY

    points = spec.discretization.points
    if points is None or spec.method not in (QMC_ONLY, AUTO):
        return
    try:
        check_points(points, spec.n, spec.m)
    except TooLarge as exc:
        raise PrecomputeLimit(f"spec.{exc.field}", exc.message) from None


class Jobs:
    """The precompute jobs of one model store directory."""

    def __init__(self, store: Path, max_basis: int, max_nodes: int, max_centres: int = 256,
                 analysis_time_limit: float = 60.0, analysis_grace: float = 2.0, *,
                 max_jobs: int = 2, max_queued: int = 16):
        self.store = Path(store)
        self.directory = self.store / "jobs"
        self.max_basis, self.max_nodes, self.max_centres = max_basis, max_nodes, max_centres
        self.analysis_time_limit, self.analysis_grace = analysis_time_limit, analysis_grace
        self.max_jobs, self.max_queued = max_jobs, max_queued

    def submit(self, spec_doc: dict[str, Any]) -> tuple[dict[str, Any], bool]:
        """Check ``spec_doc`` and start its precompute unless it is stored or running: (the job, whether
        this call started it).  SpecError names a bad field; PrecomputeLimit an oversize one."""
        from yauyau.solver.model import compile_model
        from yauyau.solver.offline.computable import check_computable
        from yauyau.solver.offline.fem import planned_nodes
        from yauyau.solver.spec import spec_from_dict
        from yauyau.storage.model_store import ModelStore, model_id

        spec = spec_from_dict(spec_doc)
        basis = spec.discretization.basis
        if basis > self.max_basis:
            raise PrecomputeLimit("spec.discretization.basis", f"{basis} basis functions: this service "
                                  f"precomputes at most {self.max_basis} (YAUYAU_MAX_PRECOMPUTE_BASIS)")
        nodes = planned_nodes(spec)
        if nodes > self.max_nodes:
            raise PrecomputeLimit("spec.discretization.mesh", f"{nodes} mesh nodes: this service precomputes "
                                  f"at most {self.max_nodes} (YAUYAU_MAX_PRECOMPUTE_NODES): set a coarser "
                                  "mesh, or run `yauyau precompute` on the spec into the service's store")
        _check_point_budget(spec)
        model = compile_model(spec)  # the expressions parse and are finite: a 4xx now, not a failed job
        check_computable(model)  # a radius, diffusion or drift beyond a double's precision: 422 now
        centres = _atlas_centres(model)
        if centres > self.max_centres:
            raise PrecomputeLimit("spec.domain.region", f"an atlas of about {centres} centres: this service "
                                  f"precomputes at most {self.max_centres} (YAUYAU_MAX_PRECOMPUTE_CENTRES)")
        spec_json = spec.canonical_json()
        mid = model_id(spec_json)
        store = ModelStore(self.store)
        if store.exists(mid):
            return self.status(mid), False
        store.ensure_writable()
        self.directory.mkdir(parents=True, exist_ok=True)
        job = {"id": mid, "status": "queued", "progress": 0.0, "done": 0, "total": basis, "error": None,
               "name": spec.name, "queued": time.time(), "started": None, "updated": time.time(), "pid": None}
        with self._queue_lock():
            jobs = self._jobs()
            if mid in jobs and not self._dead(mid, jobs[mid]):
                claimed = False  # queued or running already: the same job
            else:
                self._admit(jobs)
                claimed = self._claim(mid, job)
            if claimed:
                _write_text(self.directory / f"{mid}.spec.json", spec_json)  # only the claimer writes it
                self._dispatch({**jobs, mid: job})
        return self.status(mid), claimed

    def status(self, mid: str) -> dict[str, Any]:
        """The job of model ``mid`` (``done`` when the model is stored, whoever stored it); KeyError when
        there is no such job nor model."""
        from yauyau.storage.model_store import ModelStore

        job = _read(self._path(mid))
        stored = ModelStore(self.store).exists(mid)
        if job is None:
            if not stored:
                raise KeyError(mid)
            return {"id": mid, "status": "done", "progress": 1.0, "error": None}
        if not stored and (job.get("status") == "queued" or self._dead(mid, job)):
            self.dispatch()  # its turn may have come, or its dead process's slot is free again
            job = _read(self._path(mid)) or job
        if stored:
            job.update(status="done", progress=1.0)
        elif self._dead(mid, job):
            why = ("the precompute stopped (its process died, or the model file was removed); send the spec "
                   "again to restart it")
            job.update(status="failed", error=job.get("error") or why)
        out = {k: job.get(k) for k in ("id", "status", "progress", "error", "name")}
        if job.get("status") == "queued":
            out["position"] = self._position(mid, job)
        return out

    def dispatch(self) -> None:
        """Start the oldest queued jobs while fewer than ``max_jobs`` run (any worker, any host)."""
        if not self.directory.is_dir():
            return
        with self._queue_lock():
            self._dispatch(self._jobs())

    @contextmanager
    def _queue_lock(self):
        """The store's queue, exclusively (all workers and hosts): what runs and what waits is decided
        by one dispatcher at a time."""
        import fcntl

        with open(self.directory / "queue.lock", "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file closes
            yield

    def _jobs(self) -> dict[str, dict[str, Any]]:
        """Every job file of the store: {id: job}."""
        jobs = {}
        for path in self.directory.glob("*.json"):
            if path.name.count(".") == 1:  # <id>.json, not <id>.spec.json
                job = _read(path)
                if job is not None:
                    jobs[path.stem] = job
        return jobs

    def _running(self, jobs: dict[str, dict[str, Any]]) -> int:
        """The slots taken: jobs running, and jobs that just ended whose process has not exited yet (it
        holds its lock until then: a new process started at once would make one more than max_jobs)."""
        def busy(mid: str, job: dict[str, Any]) -> bool:
            if job.get("status") == "running":
                return not self._dead(mid, job)
            recent = time.time() - (job.get("updated") or 0) < STALE_S
            ended_now = job.get("status") in ("done", "failed") and recent
            return ended_now and _locked(self.directory / f"{mid}.lock")

        return sum(1 for mid, job in jobs.items() if busy(mid, job))

    @staticmethod
    def _queued(jobs: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
        """The queued jobs, the oldest first."""
        waiting = [job for job in jobs.values() if job.get("status") == "queued"]
        return sorted(waiting, key=lambda job: (job.get("queued") or 0.0, job.get("id") or ""))

    def _admit(self, jobs: dict[str, dict[str, Any]]) -> None:
        """QueueFull unless one more job can start now or wait among at most ``max_queued``."""
        free = max(0, self.max_jobs - self._running(jobs))
        if len(self._queued(jobs)) + 1 - free > self.max_queued:
            raise QueueFull(f"{self.max_queued} precompute jobs already wait for one of {self.max_jobs} "
                            "slots (YAUYAU_MAX_QUEUED_JOBS, YAUYAU_MAX_JOBS); send the spec again later")

    def _dispatch(self, jobs: dict[str, dict[str, Any]]) -> None:
        """Under the queue lock: start queued jobs, the oldest first, while fewer than max_jobs run."""
        from yauyau.storage.model_store import ModelStore

        running = self._running(jobs)
        for job in self._queued(jobs):
            if running >= self.max_jobs:
                break
            mid = job["id"]
            if ModelStore(self.store).exists(mid):  # stored meanwhile (another path): nothing to run
                job.update(status="done", progress=1.0, updated=time.time())
                _write(self._path(mid), job)
                continue
            job.update(status="running", started=time.time(), updated=time.time(), pid=None)
            _write(self._path(mid), job)
            self._launch(mid)
            running += 1

    def _launch(self, mid: str) -> None:
        """The job's process; when it ends, this worker dispatches again (its slot is free)."""
        process = subprocess.Popen([sys.executable, "-m", "yauyau.service.models.jobs", str(self.store), mid,
                                    repr(self.analysis_time_limit), repr(self.analysis_grace)],
                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL, start_new_session=True)  # it writes its pid

        def reap() -> None:
            process.wait()
            try:
                self.dispatch()
            except OSError:  # pragma: no cover - the store went away; the next request dispatches
                pass

        threading.Thread(target=reap, name=f"yauyau-job-{mid}", daemon=True).start()

    def _position(self, mid: str, job: dict[str, Any]) -> int:
        """1 + the queued jobs ahead of ``job``."""
        queued = self._queued(self._jobs())
        ids = [other["id"] for other in queued]
        return ids.index(mid) + 1 if mid in ids else 1

    def _path(self, mid: str) -> Path:
        return self.directory / f"{mid}.json"

    def _dead(self, mid: str, job: dict[str, Any] | None) -> bool:
        """Whether a job can be started again: none, failed, done without its model file, or running
        with its lock free (its process is gone) and either its pid written (the process took the lock
        before writing it, so it has ended) or its file silent for STALE_S seconds.  A queued job lives."""
        from yauyau.storage.model_store import ModelStore

        if job is None or job.get("status") == "failed":
            return True
        if job.get("status") == "done":
            return not ModelStore(self.store).exists(mid)
        if job.get("status") == "queued":
            return False
        if _locked(self.directory / f"{mid}.lock"):
            return False
        return job.get("pid") is not None or time.time() - (job.get("updated") or 0) > STALE_S

    def _claim(self, mid: str, job: dict[str, Any]) -> bool:
        """Write the job file unless a live job owns it (False then).  Under an exclusive lock on
        ``<id>.claim``: of the requests (threads, workers) that find a job dead at once, one claims it."""
        import fcntl

        path = self._path(mid)
        with open(self.directory / f"{mid}.claim", "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file closes
            if path.exists() and not self._dead(mid, _read(path)):
                return False
            _write(path, job)
            return True


def _read(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _write(path: Path, job: dict[str, Any]) -> None:
    """Replace the job file atomically (a reader sees the old or the new, never half)."""
    _write_text(path, json.dumps({k: job.get(k) for k in _FIELDS}))


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _locked(path: Path) -> bool:
    """Whether a job process holds ``path``'s lock (on this host)."""
    import fcntl

    try:
        with open(path, "a") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(handle, fcntl.LOCK_UN)
            return False
    except OSError:
        return False


def run(store: Path, mid: str, time_limit: float = 60.0, grace: float = 2.0) -> int:
    """The job's process: precompute the spec saved for ``mid`` into ``store``, reporting progress; the
    method analysis (method auto) is killed ``grace`` seconds after ``time_limit`` (the job then goes on
    with the bounded report's choice)."""
    import fcntl
    import threading

    from yauyau.solver.spec import spec_from_dict

    from yauyau import precompute

    path = Path(store) / "jobs" / f"{mid}.json"
    # A bare descriptor, never closed: the lock is held until the process has exited (its slot in the
    # queue is taken until then), and taken before the pid is written (a pid with a free lock: gone).
    held = os.open(path.with_suffix(".lock"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    fcntl.flock(held, fcntl.LOCK_EX)
    job = _read(path) or {"id": mid}
    job.update(status="running", pid=os.getpid(), updated=time.time())
    _write(path, job)
    lock, finished = threading.Lock(), threading.Event()

    def report(**fields: Any) -> None:
        with lock:
            job.update(fields, updated=time.time())
            _write(path, job)

    def heartbeat() -> None:  # alive while the basis is solved (no progress to report yet)
        while not finished.wait(STALE_S / 10):
            report()

    def progress(done: int, total: int) -> None:
        report(done=done, total=total, progress=done / total if total else 0.0)

    threading.Thread(target=heartbeat, daemon=True).start()

    try:
        spec = spec_from_dict(json.loads((Path(store) / "jobs" / f"{mid}.spec.json").read_text()))
        saved = precompute(spec, store, progress=progress, time_limit=time_limit, analysis_grace=grace)
        if saved != mid:
            raise RuntimeError(f"the stored id {saved} is not the job's {mid}")
    except Exception as exc:  # noqa: BLE001 - the job's answer, read by GET /v1/jobs/{id}
        finished.set()
        report(status="failed", error=f"{type(exc).__name__}: {exc}")
        return 1
    finished.set()
    report(status="done", progress=1.0)
    return 0


if __name__ == "__main__":
    sys.exit(run(Path(sys.argv[1]), sys.argv[2], *map(float, sys.argv[3:5])))
