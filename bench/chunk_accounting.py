"""Where a chunk's time goes below HTTP: timers around named functions of ``Sessions.observe``.

    python -m bench.chunk_accounting                       # this tree
    PYTHONPATH=/path/to/an/extracted/revision python -m bench.chunk_accounting   # another one

One session of the 1-D cubic sensor (SQLite store in a temporary directory), 50 chunks of 100
increments to warm up, then 600 timed, one BLAS thread; each named function (``module:attr`` or
``module:Class.attr``, those of the revision that exist) gets a wall-clock timer, reported in µs per
chunk.  The filter's own time moves by ±15% between processes of the same code (memory layout), so
compare the rows around it (the store's read and write, the file checks, the watch) between revisions,
not the totals.  What bench.trust_cost measures end to end, this splits up.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FUNCTIONS = [  # a revision's own: the session code moved to chunks.py and responses.py (issue 36)
    "yauyau.storage.session_base:SessionStoreBase.apply_chunks",
    "yauyau.service.sessions.manager:_compute_many",
    "yauyau.service.sessions.chunks:compute_many",
    "yauyau.solver.engine.filter:YauYauFilter.run_batch",
    "yauyau.storage.session_base:SessionStoreBase._write",
    "yauyau.service.sessions.manager:Sessions._chunk_job",
    "yauyau.service.sessions.manager:result_response",
    "yauyau.service.sessions.responses:result_response",
    "yauyau.service.sessions.manager:_load",
    "yauyau.service.sessions.chunks:load_state",
    "yauyau.solver.engine.filter:YauYauFilter.state_from_dict",
    "yauyau.storage.session_store:SqliteSessionStore.verify_file",
    "yauyau.storage.sqlite_files:FileWatch.look",
    "yauyau.storage.session_base:checksum",
    "yauyau.solver.watch:settle",
    "yauyau.service.sessions.manager:encode_response",
    "yauyau.service.sessions.responses:encode_response",
]
SESSION_MODULES = ("yauyau.service.sessions.manager", "yauyau.service.sessions.chunks")  # import by name


def _timed(spent: dict[str, float], spec: str) -> None:
    module_name, attr = spec.split(":")
    try:
        owner = importlib.import_module(module_name)
    except ImportError:
        return
    name = attr
    if "." in attr:
        cls, name = attr.split(".")
        owner = getattr(owner, cls, None)
    original = getattr(owner, name, None)
    if original is None:
        return

    @functools.wraps(original)
    def timed(*args, **kwargs):
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            spent[attr] = spent.get(attr, 0.0) + time.perf_counter() - start

    setattr(owner, name, timed)
    for user in SESSION_MODULES:  # a function the session modules imported by name: timed there too
        try:
            module = importlib.import_module(user)
        except ImportError:
            continue
        if getattr(module, name, None) is original:
            setattr(module, name, timed)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.chunk_accounting",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--chunks", type=int, default=600)
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits
    from yauyau.service.http.app import _open_sessions
    from yauyau.service.models.cache import Registry
    from yauyau.service.settings import Settings
    from yauyau.storage.model_store import ModelStore

    import yauyau

    spent: dict[str, float] = {}
    for spec in FUNCTIONS:
        _timed(spent, spec)
    directory = Path(tempfile.mkdtemp(prefix="yauyau-accounting-"))
    spec = yauyau.load_spec(ROOT / "examples" / "cubic_sensor.toml")
    model_id = yauyau.precompute(spec, directory / "store")
    warm = 50
    rows = np.asarray(yauyau.simulate(spec, 100 * (warm + args.chunks), seed=1).rows)
    settings = Settings(store=str(directory / "store"), session_db=str(directory / "s.sqlite3"))
    sessions = _open_sessions(settings, Registry(ModelStore(settings.store)))
    sid = sessions.create(model_id, None, None)["id"]
    with threadpool_limits(limits=1, user_api="blas"):
        for seq in range(warm + args.chunks):
            if seq == warm:
                spent.clear()
                start = time.perf_counter()
            sessions.observe(sid, seq, rows[100 * seq:100 * seq + 100].tolist(), encoded=True)
        total = time.perf_counter() - start
    print(f"revision at {Path(yauyau.__file__).resolve().parent.parent}: {1e6 * total / args.chunks:.0f} µs "
          f"per chunk in Sessions.observe")
    for name, seconds in sorted(spent.items(), key=lambda kv: -kv[1]):
        print(f"  {name}: {1e6 * seconds / args.chunks:.1f} µs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
