"""Which kernel runs the engine's rows, and where numba keeps what it compiled (numba not imported here).

``YAUYAU_KERNEL`` = ``compiled`` (the default where numba is installed): the whole-chunk row loops of
solver/engine/compiled.py; ``numpy``: the reference path of solver/engine/loops.py (one Python step a
row around the same BLAS calls).  Both give the same σ, ∫σ, log-likelihoods, moments and states to
rounding (the compiled factors' exponential is a vectorised polynomial within 2 ulp of numpy's, the
moments' sums BLAS's; tests/solver/engine/test_compiled.py: 1e-10 relative in double).  Read here
only, on each chunk: a test or a user may switch it at run time.

A one-shot command that knows its input (``yauyau filter``) calls :func:`choose_for_rows`: below
``COMPILED_MIN_ROWS`` rows it takes the numpy path for the whole process, because numba's import and
the first load of its cached loops (~1.1 s of CPU) cost more than the compiled rows save (~13 µs a
row): measured with the 1-D cubic sensor, CPU seconds of the whole command, 1 row 1.21 numpy vs
2.33 compiled, 20 000 rows 1.72 vs 2.64, 100 000 rows 4.26 vs 4.03 (bench/results/startup.md).
``YAUYAU_KERNEL`` set by the user always wins.

``YAUYAU_CACHE_DIR``: the directory numba's on-disk cache of the compiled loops goes to (default the
platform's user cache: ``$XDG_CACHE_HOME/yauyau/numba`` or ``~/.cache/yauyau/numba``, macOS
``~/Library/Caches/yauyau/numba``, Windows ``%LOCALAPPDATA%\\yauyau\\numba``), in a subdirectory named
by a digest of the kernels' sources (:func:`kernels_digest`: a changed kernel module never loads
another's stale code; an older release's directory is left, a few MB, for the user to delete).  Not
writable: the loops are compiled in memory in each process, with one warning.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path

KERNELS = ("compiled", "numpy")
COMPILED_MIN_ROWS = 100_000  # a one-shot command's break-even (module docstring)
_warned: list[str] = []
_chosen: dict[str, str] = {}  # "kernel": the process's choice by choose_for_rows, under YAUYAU_KERNEL


def enabled() -> bool:
    """True when the compiled loops run the rows (``YAUYAU_KERNEL``, default compiled where numba is)."""
    choice = os.environ.get("YAUYAU_KERNEL", "").strip().lower() or _chosen.get("kernel")
    if choice is not None and choice not in KERNELS:
        raise ValueError(f"YAUYAU_KERNEL={choice!r}: expected one of {', '.join(KERNELS)}")
    if choice == "numpy":
        return False
    if choice is None:
        return _numba_installed()
    return True  # asked for: a missing numba raises ImportError on first use


@contextmanager
def one_shot() -> Iterator[None]:
    """The span of a one-shot command: a choice made by :func:`choose_for_rows` inside ends with it."""
    try:
        yield
    finally:
        _chosen.pop("kernel", None)


def choose_for_rows(rows: int, min_rows: int = COMPILED_MIN_ROWS) -> str:
    """The kernel a command that will step ``rows`` rows in all and exit should take (module docstring):
    numpy below ``min_rows`` (the filter's break-even: ``COMPILED_MIN_ROWS`` for the general engine, a
    filter's own ``compiled_min_rows`` where its compiled rows save more) unless ``YAUYAU_KERNEL`` says
    otherwise; kept until the end of the enclosing :func:`one_shot`."""
    if not os.environ.get("YAUYAU_KERNEL", "").strip() and rows < min_rows:
        _chosen["kernel"] = "numpy"
    else:
        _chosen.pop("kernel", None)
    return "compiled" if enabled() else "numpy"


def _numba_installed() -> bool:
    return "numba" in sys.modules or importlib.util.find_spec("numba") is not None  # imported: no search


def cache_dir() -> Path:
    """``YAUYAU_CACHE_DIR``, else the platform's user cache directory + yauyau/numba."""
    given = os.environ.get("YAUYAU_CACHE_DIR")
    if given:
        return Path(given).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "yauyau" / "numba"


@lru_cache(maxsize=1)
def kernels_digest() -> str:
    """A digest of the sources of every solver module that mentions numba (the kernels and what they
    inline from each other).  The cache lives in a directory of that name: numba checks only the file
    that defines a function, so a kernel that inlines another module's function (compiled_batch.py's
    ``fused_row`` from compiled.py) would otherwise be loaded stale after only that module changed."""
    root = Path(__file__).resolve().parent
    digest = hashlib.blake2b(digest_size=8)
    for path, text in kernel_sources():
        digest.update(path.relative_to(root).as_posix().encode() + b"\0" + text)
    return digest.hexdigest()


def kernel_sources() -> list[tuple[Path, bytes]]:
    """(path, contents) of the solver's modules that mention numba, in a fixed order."""
    root = Path(__file__).resolve().parent
    found = ((path, path.read_bytes()) for path in sorted(root.rglob("*.py")))
    return [(path, text) for path, text in found if b"numba" in text]


def writable_cache_dir() -> Path | None:
    """:func:`cache_dir` / :func:`kernels_digest` made and checked writable, or None (compile in memory)
    with a warning, once."""
    path = cache_dir() / kernels_digest()
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as error:
        if str(path) not in _warned:
            _warned.append(str(path))
            warnings.warn(f"yauyau: numba cache directory {path} is not writable ({error.strerror}); "
                          "compiling the row loops in memory (set YAUYAU_CACHE_DIR)", RuntimeWarning,
                          stacklevel=3)
        return None
    return path
