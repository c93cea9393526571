#!/usr/bin/env python3
"""Set up, precompute and serve yauyau: the one script the Dockerfile, dev.py and the tests use.

    python3 scripts/provision.py install    --venv DIR [--editable] [--extras test]
    python3 scripts/provision.py browser
    python3 scripts/provision.py precompute --venv DIR --store DIR SPEC.toml ...
    python3 scripts/provision.py serve      --venv DIR --store DIR [--host H] [--port P]

Standard library only: it runs on a bare ``python3`` before anything is installed.  ``install``
creates the virtual environment and pip-installs this checkout into it; ``precompute`` solves the
offline stage of each spec whose model is not in the store yet; ``serve`` replaces itself with
``yauyau serve``.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
STAMP = ".yauyau-installed"


def venv_bin(venv_dir: Path, name: str) -> Path:
    sub = "Scripts" if os.name == "nt" else "bin"
    return venv_dir / sub / (name + (".exe" if os.name == "nt" else ""))


def _say(message: str) -> None:
    print(f"[provision] {message}", file=sys.stderr, flush=True)


def _install_key(editable: bool, extras: str) -> str:
    """Changes when the dependencies or the way of installing change (then pip runs again)."""
    text = (ROOT / "pyproject.toml").read_bytes() + f"|{editable}|{extras}|{sys.version}".encode()
    return hashlib.sha256(text).hexdigest()


def defined_extras() -> list[str]:
    """The extras pyproject.toml defines ([project.optional-dependencies])."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return list(project.get("optional-dependencies", {}))


def unknown_extras(extras: str) -> list[str]:
    """The extras named in ``extras`` ("test,...") that pyproject.toml does not define (pip only warns)."""
    defined = defined_extras()
    return [name for name in (e.strip() for e in extras.split(",")) if name and name not in defined]


def install(venv_dir: Path, editable: bool = False, extras: str = "") -> None:
    """Create ``venv_dir`` if needed and install this checkout (skipped when already done); an extra
    that pyproject.toml does not define is refused before anything is installed."""
    unknown = unknown_extras(extras)
    if unknown:
        defined = ", ".join(defined_extras()) or "none"
        raise SystemExit(f"[provision] --extras: {', '.join(unknown)} not defined in pyproject.toml "
                         f"[project.optional-dependencies] (defined: {defined})")
    venv_dir = venv_dir.resolve()
    key = _install_key(editable, extras)
    stamp = venv_dir / STAMP
    if stamp.is_file() and stamp.read_text().strip() == key and venv_bin(venv_dir, "yauyau").exists():
        return
    if not venv_bin(venv_dir, "python").exists():
        _say(f"creating virtual environment {venv_dir}")
        venv.EnvBuilder(with_pip=True).create(venv_dir)
    target = f"{ROOT}[{extras}]" if extras else str(ROOT)
    command = [str(venv_bin(venv_dir, "python")), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    command += ["-e", target] if editable else [target]
    _say("installing: " + " ".join(command[3:]))
    subprocess.run(command, check=True, cwd=ROOT)
    stamp.write_text(key + "\n")


_EXISTS = """
import sys
from yauyau.solver.spec import load_spec
from yauyau.storage.model_store import ModelStore, model_id
spec = load_spec(sys.argv[1])
print(ModelStore(sys.argv[2]).exists(model_id(spec.canonical_json())))
"""


def precompute(venv_dir: Path, store: Path, specs: list[Path]) -> None:
    """Precompute every spec whose model is missing from ``store``."""
    python = str(venv_bin(venv_dir, "python"))
    for spec in specs:
        probe = subprocess.run([python, "-c", _EXISTS, str(spec), str(store)], check=True,
                               capture_output=True, text=True)
        if probe.stdout.strip() == "True":
            _say(f"{spec}: already in {store}")
            continue
        _say(f"{spec}: precomputing into {store}")
        subprocess.run([str(venv_bin(venv_dir, "yauyau")), "precompute", str(spec), "--store", str(store)],
                       check=True)


# Debian packages the tests drive: the live page's browser, and curl for the docs' walk-throughs
BROWSER = {"/usr/bin/chromium": "chromium", "/usr/bin/chromedriver": "chromium-driver",
           "/usr/bin/curl": "curl"}


def browser() -> None:
    """Debian's chromium and chromedriver for the live-page test (tests/service/http/test_live_page.py)
    and curl for the walk-throughs of docs/ (tests/docs/test_readme_streams.py): installed with apt-get
    when missing and this runs as root; otherwise say what to install (the test then fails with the
    reason; it never skips)."""
    missing = [package for path, package in BROWSER.items() if not Path(path).exists()]
    _apt_install(missing, "the browser test")


def postgres() -> None:
    """Debian's PostgreSQL server for the tests of the shared session store (scripts/pg_server.py starts
    one in a temporary directory): installed with apt-get when missing, as :func:`browser` does."""
    import glob
    import shutil

    found = shutil.which("initdb") or glob.glob("/usr/lib/postgresql/*/bin/initdb")
    _apt_install([] if found else ["postgresql"], "the PostgreSQL session-store tests")


def _apt_install(missing: list[str], why: str) -> None:
    import shutil

    if not missing:
        return
    apt = shutil.which("apt-get")
    if apt is None or os.geteuid() != 0:
        _say(f"{why} need(s) {' and '.join(missing)}: sudo apt-get install {' '.join(missing)}")
        return
    _say(f"installing {' '.join(missing)} (apt-get) for {why}")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    quiet = {"stdout": subprocess.DEVNULL, "env": env}
    if subprocess.run([apt, "install", "-y", "-q", *missing], **quiet).returncode != 0:
        subprocess.run([apt, "update", "-q"], check=True, **quiet)
        subprocess.run([apt, "install", "-y", "-q", *missing], check=True, **quiet)


def serve(venv_dir: Path, store: Path, host: str | None, port: int | None, workers: int | None) -> None:
    """Replace this process with ``yauyau serve`` (signals reach the server directly)."""
    command = [str(venv_bin(venv_dir, "yauyau")), "serve", "--store", str(store)]
    for flag, value in (("--host", host), ("--port", port), ("--workers", workers)):
        if value is not None:
            command += [flag, str(value)]
    _say("serving: " + " ".join(command))
    sys.stdout.flush()
    os.execv(command[0], command)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("browser")
    for name in ("install", "precompute", "serve"):
        p = sub.add_parser(name)
        p.add_argument("--venv", type=Path, required=True)
        if name == "install":
            p.add_argument("--editable", action="store_true")
            p.add_argument("--extras", default="")
        else:
            p.add_argument("--store", type=Path, required=True)
        if name == "precompute":
            p.add_argument("specs", nargs="+", type=Path)
        if name == "serve":
            p.add_argument("--host")
            p.add_argument("--port", type=int)
            p.add_argument("--workers", type=int)
    args = parser.parse_args(argv)
    try:
        if args.command == "browser":
            browser()
        elif args.command == "install":
            install(args.venv, args.editable, args.extras)
        elif args.command == "precompute":
            precompute(args.venv, args.store, args.specs)
        else:
            serve(args.venv, args.store, args.host, args.port, args.workers)
    except subprocess.CalledProcessError as exc:
        _say(f"failed ({exc.returncode}): {' '.join(map(str, exc.cmd))[:300]}")
        return exc.returncode or 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
