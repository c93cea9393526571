"""Models added at run time: ``POST /v1/models`` precomputes a spec as a background job.

The job's id is the model id (the content hash of the canonical spec), so the same spec sent twice,
to any worker of any server sharing the model store, is one job and is computed once: the job is a
file ``<store>/jobs/<id>.json`` created exclusively (``O_EXCL``) by the request that starts it.  The
precompute runs in a process of its own (``python -m yauyau.service.jobs STORE ID``: the serving
worker stays free), which writes its progress (propagators solved / basis size) into that file,
then ``done`` once the model file is saved — it then appears in ``GET /v1/models`` — or ``failed``
with the reason.  The job's process holds an exclusive lock on ``<id>.lock`` for its lifetime (the
heartbeat alone is not enough: the eigensolve holds the GIL for minutes); a job whose lock is free
and whose file has been silent for ``STALE_S`` seconds died (its host restarted) and may be started
again by the next request.  A job is claimed under an exclusive lock on ``<id>.claim``, so of the
requests that find it missing or dead at once, one starts it.  Before any
work, a spec is checked (the spec's own rules, field by field) and refused with a 413 problem when
it is larger than the service allows (basis size, mesh nodes, atlas centres:
``YAUYAU_MAX_PRECOMPUTE_BASIS``/``_NODES``/``_CENTRES``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

STALE_S = 120.0  # a running job silent this long, whose lock is not held on this host, is taken as dead
_FIELDS = ("id", "status", "progress", "done", "total", "error", "name", "started", "updated", "pid")


class PrecomputeLimit(Exception):
    """A spec larger than the service precomputes (413): ``field`` says which size, ``message`` why."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def _atlas_centres(model: Any) -> int:
    """About how many balls an atlas ([domain] region) asks for (the lattice before its spacing is
    rounded to whole elements); 0 without one."""
    from yauyau.solver.atlas import lattice, needs_atlas

    if not needs_atlas(model):
        return 0
    return lattice(model).size


class Jobs:
    """The precompute jobs of one model store directory."""

    def __init__(self, store: Path, max_basis: int, max_nodes: int, max_centres: int = 256,
                 analysis_time_limit: float = 60.0, analysis_grace: float = 2.0):
        self.store = Path(store)
        self.directory = self.store / "jobs"
        self.max_basis, self.max_nodes, self.max_centres = max_basis, max_nodes, max_centres
        self.analysis_time_limit, self.analysis_grace = analysis_time_limit, analysis_grace

    def submit(self, spec_doc: dict[str, Any]) -> tuple[dict[str, Any], bool]:
        """Check ``spec_doc`` and start its precompute unless it is stored or running: (the job, whether
        this call started it).  SpecError names a bad field; PrecomputeLimit an oversize one."""
        from yauyau.solver.computable import check_computable
        from yauyau.solver.fem import planned_nodes
        from yauyau.solver.model import compile_model
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
                                  f"at most {self.max_nodes} (YAUYAU_MAX_PRECOMPUTE_NODES)")
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
        job = {"id": mid, "status": "running", "progress": 0.0, "done": 0, "total": basis, "error": None,
               "name": spec.name, "started": time.time(), "updated": time.time(), "pid": None}
        if not self._claim(mid, job):
            return self.status(mid), False
        _write_text(self.directory / f"{mid}.spec.json", spec_json)  # only the claimer writes it
        subprocess.Popen([sys.executable, "-m", "yauyau.service.jobs", str(self.store), mid,
                          repr(self.analysis_time_limit), repr(self.analysis_grace)],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)  # it writes its pid and its progress itself
        return self.status(mid), True

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
        if stored:
            job.update(status="done", progress=1.0)
        elif self._dead(mid, job):
            why = ("the precompute stopped (its process died, or the model file was removed); send the spec "
                   "again to restart it")
            job.update(status="failed", error=job.get("error") or why)
        return {k: job.get(k) for k in ("id", "status", "progress", "error", "name")}

    def _path(self, mid: str) -> Path:
        return self.directory / f"{mid}.json"

    def _dead(self, mid: str, job: dict[str, Any] | None) -> bool:
        """Whether a job can be started again: none, failed, done without its model file, or running
        with its lock free (its process is gone) and its file silent for STALE_S seconds."""
        from yauyau.storage.model_store import ModelStore

        if job is None or job.get("status") == "failed":
            return True
        if job.get("status") == "done":
            return not ModelStore(self.store).exists(mid)
        return not _locked(self.directory / f"{mid}.lock") and time.time() - job.get("updated", 0) > STALE_S

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
    import threading

    from yauyau.solver.spec import spec_from_dict

    from yauyau import precompute

    path = Path(store) / "jobs" / f"{mid}.json"
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
