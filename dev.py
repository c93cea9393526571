#!/usr/bin/env python3
"""Developer entry point; needs only python3.

    python3 dev.py serve          # venv + install, precompute the bundled examples if missing, serve on :8000
    python3 dev.py test           # venv + install (with test tools, the test browser and PostgreSQL), run
                                  # every test (what CI runs)
    python3 dev.py test --fast    # the fast tier: no test marked slow, service (a real `yauyau serve`),
                                  # browser or postgres; under 3 minutes on 2 cores
    python3 dev.py test tests/solver/test_spec.py -x   # what you name, in one process

Both tiers run the test files in parallel, one per core (pytest-xdist, ``-n auto --dist loadfile``);
``--fast`` may be followed by more pytest arguments, anything else replaces the defaults.  The markers
are declared in pyproject.toml ([tool.pytest.ini_options]).

The virtual environment is ``.venv`` beside this file (``YAUYAU_VENV`` overrides); pip runs again
only when pyproject.toml changed.  The steps are those of scripts/provision.py, which the
Dockerfile runs too.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT / "scripts"))
import provision  # noqa: E402

VENV = Path(os.environ.get("YAUYAU_VENV", ROOT / ".venv"))
STORE = Path(os.environ.get("YAUYAU_STORE", ROOT / "var" / "store"))
EXAMPLES = [ROOT / "examples" / "cubic_sensor.toml", ROOT / "examples" / "power_meter.toml"]
# the test tools; the benchmarks need nothing more here (their peers, particles and FilterPy, pin numpy < 2
# and run in a venv of their own: python -m bench.measurements --setup-peers)
EXTRAS = "test"


def serve(args: list[str]) -> int:
    provision.install(VENV, editable=True, extras=EXTRAS)
    provision.precompute(VENV, STORE, EXAMPLES)
    port = int(os.environ.get("YAUYAU_PORT", "8000"))
    provision.serve(VENV, STORE, os.environ.get("YAUYAU_HOST", "127.0.0.1"), port, None)
    return 0  # not reached: serve replaces this process


PARALLEL = ["-n", "auto", "--dist", "loadfile"]
FAST = ["-m", "not slow and not service and not browser and not postgres"]


def test(args: list[str]) -> int:
    fast = args[:1] == ["--fast"]
    provision.install(VENV, editable=True, extras=EXTRAS)
    if not fast:  # the fast tier needs neither
        provision.browser()  # Debian's chromium + chromedriver for tests/service/http/test_live_page.py
        provision.postgres()  # Debian's PostgreSQL server for the shared session store's tests
    # the files run in parallel, one per core (pytest-xdist; a file's tests stay together, so its module
    # fixtures are built once); arguments given replace that, except after --fast
    chosen = [*FAST, *PARALLEL, *args[1:]] if fast else (args or PARALLEL)
    command = [str(provision.venv_bin(VENV, "python")), "-m", "pytest", "-q", *chosen]
    return subprocess.run(command, cwd=ROOT).returncode


def main() -> int:
    commands = {"serve": serve, "test": test}
    if len(sys.argv) < 2 or sys.argv[1] not in commands:
        print(__doc__, file=sys.stderr)
        return 2
    try:
        return commands[sys.argv[1]](sys.argv[2:])
    except subprocess.CalledProcessError as exc:
        print(f"dev.py: step failed with status {exc.returncode}", file=sys.stderr)
        return exc.returncode or 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
