"""`yauyau precompute` / `yauyau models` through the real console script (subprocesses)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.spec import load_spec
from yauyau.storage.model_store import ModelStore, model_id

YAUYAU = str(Path(sys.executable).with_name("yauyau"))
OU = (ROOT / "examples" / "ou.toml").read_text()


def yauyau(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([YAUYAU, *args], capture_output=True, text=True, timeout=120, env=env, cwd=ROOT)


def small_ou(tmp_path: Path, basis: int = 6) -> Path:
    path = tmp_path / "ou.toml"
    path.write_text(OU.replace("basis = 96", f"basis = {basis}"))
    return path


@pytest.mark.slow
def test_precompute_prints_id_last_and_models_lists_it(tmp_path: Path):
    spec_path, store = small_ou(tmp_path), tmp_path / "store"
    done = yauyau("precompute", str(spec_path), "--store", str(store))
    assert done.returncode == 0, done.stderr
    mid = done.stdout.strip().splitlines()[-1]
    assert mid == model_id(load_spec(spec_path).canonical_json())
    assert (store / f"{mid}.h5").is_file() and "stored" in done.stderr

    stored = ModelStore(store).load(mid)
    # the stored projector inverts the stored basis: c = P Φ c (L² projection of basis functions)
    assert np.allclose(stored.arrays["projector"] @ stored.arrays["basis"], np.eye(6), atol=1e-8)
    assert stored.attrs["workers"] >= 1 and stored.attrs["precompute_seconds"] >= 0

    again = yauyau("precompute", str(spec_path), "--store", str(store), "--quiet")
    assert again.returncode == 0 and again.stdout.strip() == mid and again.stderr == ""

    listed = yauyau("models", "--store", str(store), "--json")
    assert listed.returncode == 0
    [row] = json.loads(listed.stdout)
    assert (row["id"], row["name"], row["n"], row["m"], row["basis"], row["dt"], row["radius"]) == (
        mid, "ornstein-uhlenbeck", 1, 1, 6, 0.01, 8.0)
    text = yauyau("models", "--store", str(store))
    assert text.returncode == 0 and mid in text.stdout and "ornstein-uhlenbeck" in text.stdout


@pytest.mark.slow
def test_force_recomputes_and_replaces_with_compress(tmp_path: Path):
    spec_path, store = small_ou(tmp_path, basis=4), tmp_path / "store"
    first = yauyau("precompute", str(spec_path), "--store", str(store), "--quiet", "--workers", "1")
    created = ModelStore(store).load(first.stdout.strip()).attrs["precompute_seconds"]
    forced = yauyau("precompute", str(spec_path), "--store", str(store), "--force", "--compress")
    assert forced.returncode == 0 and forced.stdout.strip() == first.stdout.strip()
    assert "already" not in forced.stderr and created >= 0
    assert [p.name for p in store.iterdir()] == [f"{first.stdout.strip()}.h5"]
    with h5py.File(store / f"{first.stdout.strip()}.h5", "r") as h5:
        assert h5["arrays"]["propagator_fp"].compression == "gzip"


def _replace(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new)


HOSTILE = [
    ("drift[0]", lambda s: _replace(s, '"-theta*x"', json.dumps("__import__('os').system('x')"))),
    ("drift[0]", lambda s: _replace(s, '"-theta*x"', json.dumps("(1).__class__"))),
    ("drift[0]", lambda s: _replace(s, '"-theta*x"', json.dumps("lambda: 0"))),
    ("drift[0]", lambda s: _replace(s, '"-theta*x"', json.dumps("9**9**9"))),
    ("drift[0]", lambda s: _replace(s, '"-theta*x"', '"-theta*zeta"')),
    ("drift", lambda s: _replace(s, 'drift = ["-theta*x"]', 'drift = ["-theta*x", "x"]')),
    ("diffusion", lambda s: _replace(s, "[initial]", "diffusion = [[-1.0]]\n\n[initial]")),
    ("domain.radius", lambda s: _replace(s, "radius = 8.0", "radius = 0.0")),
    ("domain.radius", lambda s: _replace(s, "radius = 8.0", "radius = -3.0")),
]


@pytest.mark.parametrize("field, edit", HOSTILE, ids=[f"{f}-{i}" for i, (f, _) in enumerate(HOSTILE)])
def test_hostile_spec_exits_2_naming_the_field_and_writes_nothing(tmp_path: Path, field, edit):
    spec_path, store = tmp_path / "bad.toml", tmp_path / "store"
    spec_path.write_text(edit(OU.replace("basis = 96", "basis = 4")))
    done = yauyau("precompute", str(spec_path), "--store", str(store))
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith(f"yauyau precompute: error: {field}:"), done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    assert done.stdout == "" and not store.exists()
    assert not (tmp_path / "x").exists()  # os.system('x') never ran


def test_unwritable_store_and_bad_workers_exit_2(tmp_path: Path):
    spec_path, blocker = small_ou(tmp_path), tmp_path / "file"
    blocker.write_text("not a directory")
    done = yauyau("precompute", str(spec_path), "--store", str(blocker / "store"))
    assert done.returncode == 2 and done.stderr.startswith("yauyau precompute: error: store:")
    assert "Traceback" not in done.stderr and done.stdout == ""
    done = yauyau("precompute", str(spec_path), "--store", str(tmp_path / "s"), "--workers", "0")
    assert done.returncode == 2 and "workers" in done.stderr and not (tmp_path / "s").exists()
    missing = yauyau("models", "--store", str(tmp_path / "nowhere"))
    assert missing.returncode == 2 and missing.stderr.startswith("yauyau models: error: store:")


NIU_4D = """name = "niu-4d"
state = ["a", "b", "c", "d"]
drift = ["-a", "-b", "-c", "-d"]
observation = ["a + b", "c + d"]
method = "yau-niu"
[initial]
kind = "gaussian"
mean = [0.0, 0.0, 0.0, 0.0]
cov = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
[domain]
radius = 8.0
[discretization]
dt = 0.01
basis = 64
points = POINTS
"""


def test_a_point_budget_beyond_memory_exits_2_naming_it(tmp_path: Path):
    """10^12 yau-niu points in 4-D (over 300 TB): exit 2 before any allocation, one line naming
    discretization.points, the memory it would need, this machine's and the budget that fits; that
    budget itself is accepted."""
    from yauyau.solver.qmc.budget import memory_limit, memory_needed

    spec_path, store = tmp_path / "big.toml", tmp_path / "store"
    spec_path.write_text(NIU_4D.replace("POINTS", str(10**12)))
    done = yauyau("precompute", str(spec_path), "--store", str(store))
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("yauyau precompute: error: discretization.points: "), done.stderr
    line = done.stderr.strip()
    assert len(line.splitlines()) == 1 and "Traceback" not in line
    need, limit = memory_needed(10**12, 4, 2, 2), memory_limit()
    assert f"{need / 2**30:.1f} GiB" in line and f"{limit / 2**30:.1f} GiB this machine has" in line
    fits = int(line.split("at most ")[1].split()[0])
    assert memory_needed(fits, 4, 2, 2) <= limit < memory_needed(fits + 1, 4, 2, 2)
    assert done.stdout == "" and not any(store.glob("*.h5"))
