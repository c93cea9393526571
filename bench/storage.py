"""Storage benchmark: HDF5 file size and write/load time per dataset filter policy, and the
session store's chunk throughput (1 vs 2 processes, and contention on one session).

    python -m bench.storage [--quick]      # writes bench/results/storage.md

Sizes are exact; times are ratios against the plain (unfiltered) layout measured in the same run.
"""

from __future__ import annotations

import argparse
import multiprocessing
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
from yauyau.solver import compile_model, load_spec
from yauyau.solver.offline.pipeline import precompute
from yauyau.storage.model_store import ModelStore
from yauyau.storage.session_store import SqliteSessionStore

ROOT = Path(__file__).resolve().parent.parent
FRAGMENT = ROOT / "bench" / "results" / "storage.md"
POLICIES = {
    "plain (no checksum)": lambda arr: {},
    "fletcher32": lambda arr: {"fletcher32": True, "chunks": True},
    "fletcher32 + shuffle/lzf, all": lambda arr: {"fletcher32": True, "chunks": True, "shuffle": True,
                                                   "compression": "lzf"},
    "fletcher32 + shuffle/gzip-4, all": lambda arr: {"fletcher32": True, "chunks": True, "shuffle": True,
                                                      "compression": "gzip", "compression_opts": 4},
}
CHOSEN = "ModelStore default: fletcher32, shuffle/gzip-4 on integers"
CHOSEN_GZ = "ModelStore(compress_floats=True), `precompute --compress`"


def offline_arrays(example: str, basis: int | None) -> tuple[str, dict[str, np.ndarray]]:
    spec = load_spec(ROOT / "examples" / example)
    if basis is not None:
        coarser = spec.discretization.model_copy(update={"basis": basis})
        spec = spec.model_copy(update={"discretization": coarser})
    return spec.canonical_json(), precompute(compile_model(spec)).to_arrays()


def _write_plain(path: Path, arrays: dict[str, np.ndarray], policy) -> None:
    with h5py.File(path, "w") as h5:
        for name, arr in arrays.items():
            stored = arr.reshape(1) if arr.ndim == 0 else arr
            h5.create_dataset(name, data=stored, **policy(stored))


def _read_plain(path: Path) -> None:
    with h5py.File(path, "r") as h5:
        for name in h5:
            h5[name][()]


def _best(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def file_policies(spec_json: str, arrays: dict[str, np.ndarray], repeats: int, workdir: Path) -> list[tuple]:
    rows = []
    for label, policy in POLICIES.items():
        path = workdir / f"{len(rows)}.h5"
        write = _best(lambda p=path, f=policy: _write_plain(p, arrays, f), repeats)
        load = _best(lambda p=path: _read_plain(p), repeats)
        rows.append((label, path.stat().st_size, write, load))
    store = ModelStore(workdir / "store")
    mid = store.save(spec_json, arrays)
    write = _best(lambda: store.save(spec_json, arrays), repeats)  # + fsync and rename
    load = _best(lambda: store.load(mid), repeats)  # + hash and metadata checks
    rows.append((CHOSEN, store.path(mid).stat().st_size, write, load))
    store = ModelStore(workdir / "store-gz", compress_floats=True)
    mid = store.save(spec_json, arrays)
    write = _best(lambda: store.save(spec_json, arrays), repeats)
    load = _best(lambda: store.load(mid), repeats)
    rows.append((CHOSEN_GZ, store.path(mid).stat().st_size, write, load))
    return rows


def _chunk(seq: int):
    def compute(state: dict) -> tuple[dict, dict]:
        return {"c": state["c"], "step": state["step"] + 1}, {"seq": seq, "mean": state["c"][:2]}
    return compute


def _apply_many(path: str, sid: str, chunks: int) -> None:
    store = SqliteSessionStore(path)
    for seq in range(chunks):
        store.apply_chunk(sid, seq, _chunk(seq))


def _contend(path: str, sid: str, chunks: int) -> None:
    store = SqliteSessionStore(path)
    while (next_seq := store.get(sid).next_seq) < chunks:
        store.apply_chunk(sid, next_seq, _chunk(next_seq))


def session_throughput(chunks: int, workdir: Path) -> list[tuple[str, float]]:
    """Chunks per second with a 96-coefficient state (the size of a small Yau–Yau state)."""
    path = str(workdir / "sessions.sqlite")
    store = SqliteSessionStore(path)
    state = {"c": list(np.linspace(0, 1, 96)), "step": 0}
    ctx = multiprocessing.get_context("fork")
    out = []
    for label, procs, shared in (("1 process, 1 session", 1, False), ("2 processes, own sessions", 2, False),
                                 ("2 processes, one session (contention)", 2, True)):
        sids = [store.create("m", "bench", state) for _ in range(1 if shared else procs)]
        target = _contend if shared else _apply_many
        workers = [ctx.Process(target=target, args=(path, sids[0 if shared else i], chunks))
                   for i in range(procs)]
        start = time.perf_counter()
        for p in workers:
            p.start()
        for p in workers:
            p.join()
        elapsed = time.perf_counter() - start
        out.append((label, (chunks if shared else chunks * procs) / elapsed))
    return out


def report(model_rows: dict[str, list[tuple]], sessions: list[tuple[str, float]], command: str) -> str:
    lines = ["## Storage", "", f"`{command}`", "",
             "HDF5 model files: size and best-of-runs write/load time relative to the plain layout.", ""]
    for model, rows in model_rows.items():
        plain = rows[0]
        lines += [f"**{model}** (plain: write {plain[2] * 1e3:.1f} ms, load {plain[3] * 1e3:.1f} ms)", "",
                  "| layout | size (KiB) | size ratio | write ratio | load ratio |",
                  "|---|---:|---:|---:|---:|"]
        for label, size, write, load in rows:
            lines.append(f"| {label} | {size / 1024:.0f} | {size / plain[1]:.3f} | {write / plain[2]:.2f} | "
                         f"{load / plain[3]:.2f} |")
        lines.append("")
    base = sessions[0][1]
    lines += ["SQLite session store, `apply_chunk` with a 96-coefficient JSON state "
              "(WAL, synchronous=NORMAL):",
              "", "| workload | chunks/s | ratio to 1 process |", "|---|---:|---:|"]
    lines += [f"| {label} | {rate:.0f} | {rate / base:.2f} |" for label, rate in sessions]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.storage")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    repeats, chunks = (3, 100) if args.quick else (15, 500)
    cases = [("ou.toml", 32 if args.quick else None), ("range_2d.toml", 64 if args.quick else None)]
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(tmp)
        model_rows = {}
        for example, basis in cases:
            spec_json, arrays = offline_arrays(example, basis)
            shapes = ", ".join(f"{k} {v.shape}" for k, v in arrays.items() if k.startswith("prop"))
            model_rows[f"{example} ({shapes})"] = file_policies(spec_json, arrays, repeats, workdir)
        sessions = session_throughput(chunks, workdir)
    command = "python -m bench.storage" + (" --quick" if args.quick else "")
    FRAGMENT.write_text(report(model_rows, sessions, command))
    print(FRAGMENT.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
