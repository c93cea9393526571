"""The Docker image's steps, run here: scripts/provision.py installs this checkout into a FRESH
virtual environment, precomputes the example model, and serves it; the API then answers.

This is what the Dockerfile runs (install, precompute at build time; serve as the command),
so a missing dependency or a broken entry point fails here even without a Docker engine.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import httpx
import pytest
from helpers import ROOT, free_port

pytestmark = pytest.mark.service  # a real `yauyau serve` process

PROVISION = [sys.executable, str(ROOT / "scripts" / "provision.py")]


def _wait(url: str, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        try:
            if httpx.get(url, timeout=1.0).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise AssertionError(f"{url} never answered")


_IMPORTS = """
import importlib, json
found = {}
for name in ("yauyau", "yauyau.solver", "yauyau.storage", "yauyau.service", "yauyau.service.cli",
             "solver", "storage", "service"):
    try:
        found[name] = importlib.import_module(name).__file__
    except ImportError:
        found[name] = None
print(json.dumps(found))
"""


def _assert_one_import_name(python: Path, cwd: Path) -> None:
    """The install puts one top-level name in site-packages: yauyau (its layers under it)."""
    import json

    out = subprocess.run([str(python), "-c", _IMPORTS], cwd=cwd, check=True, capture_output=True, text=True,
                         env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    found = json.loads(out.stdout)
    for name in ("yauyau", "yauyau.solver", "yauyau.storage", "yauyau.service", "yauyau.service.cli"):
        assert found[name] is not None and "site-packages" in found[name], (name, found[name])
    assert found["solver"] is None and found["storage"] is None and found["service"] is None, found
    site = Path(found["yauyau"]).parent.parent
    assert not any((site / name).exists() for name in ("solver", "storage", "service"))


@pytest.mark.slow
def test_fresh_install_precompute_and_serve(tmp_path):
    venv, store = tmp_path / "venv", tmp_path / "store"
    subprocess.run([*PROVISION, "install", "--venv", str(venv)], check=True, cwd=tmp_path, timeout=600)
    assert (venv / "bin" / "yauyau").exists()
    _assert_one_import_name(venv / "bin" / "python", tmp_path)
    spec = str(ROOT / "examples" / "cubic_sensor.toml")
    subprocess.run([*PROVISION, "precompute", "--venv", str(venv), "--store", str(store), spec],
                   check=True, cwd=tmp_path, timeout=300)
    again = subprocess.run([*PROVISION, "precompute", "--venv", str(venv), "--store", str(store), spec],
                           check=True, cwd=tmp_path, timeout=300, capture_output=True, text=True)
    assert "already in" in again.stderr  # the build step is idempotent
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("YAUYAU_", "PYTHONPATH"))}
    serve = [*PROVISION, "serve", "--venv", str(venv), "--store", str(store), "--port", str(port)]
    proc = subprocess.Popen(serve, cwd=tmp_path, env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    url = f"http://127.0.0.1:{port}"
    try:
        _wait(url + "/livez", proc)
        _wait(url + "/readyz", proc)
        models = httpx.get(url + "/v1/models").json()
        assert [m["name"] for m in models] == ["cubic-sensor"]
        created = httpx.post(url + "/v1/sessions", json={"model": models[0]["id"]})
        assert created.status_code == 201
        assert created.json()["estimate"]["mean"][0] == pytest.approx(0.5, abs=1e-3)  # the prior N(0.5, 1)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        proc.stderr.close()


def test_the_scripts_ask_only_for_extras_pyproject_defines(tmp_path):
    """dev.py asked for "test,bench" and pyproject.toml defines no bench (pip only warns): every --extras
    and EXTRAS in dev.py, scripts/provision.py, the Dockerfile and .ci/run names a defined extra, and
    provision refuses an undefined one before creating anything."""
    defined = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])
    named = []
    for name in ("dev.py", "scripts/provision.py", "Dockerfile", ".ci/run"):
        text = (ROOT / name).read_text()
        named += re.findall(r'^EXTRAS = "([^"]*)"', text, re.M) + re.findall(r"--extras[ =]([\w,-]+)", text)
    assert named and all(set(extras.split(",")) <= defined for extras in named), (named, defined)
    venv = tmp_path / "venv"
    done = subprocess.run([*PROVISION, "install", "--venv", str(venv), "--extras", "test,bench"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stderr
    assert "--extras: bench not defined in pyproject.toml" in done.stderr, done.stderr
    assert not venv.exists()
