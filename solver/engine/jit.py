"""Which kernel runs the engine's rows, and where numba keeps what it compiled (numba not imported here).

``YAUYAU_KERNEL`` = ``compiled`` (the default where numba is installed): the whole-chunk row loops of
solver/engine/compiled.py; ``numpy``: the reference path of solver/engine/loops.py (one Python step a
row around the same BLAS calls).  Both give the same σ, ∫σ, log-likelihoods and states bit for bit
where numpy's exp is libm's, the moments to rounding (BLAS sums; fused chunks, solver/engine/fused.py:
1e-12 relative in double; tests/solver/engine/test_compiled.py).  Read here only, on each chunk: a
test or a user may switch it at run time.

``YAUYAU_CACHE_DIR``: the directory numba's on-disk cache of the compiled loops goes to (default the
platform's user cache: ``$XDG_CACHE_HOME/yauyau/numba`` or ``~/.cache/yauyau/numba``, macOS
``~/Library/Caches/yauyau/numba``, Windows ``%LOCALAPPDATA%\\yauyau\\numba``).  Not writable: the loops
are compiled in memory in each process, with one warning.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
import warnings
from pathlib import Path

KERNELS = ("compiled", "numpy")
_warned: list[str] = []


def enabled() -> bool:
    """True when the compiled loops run the rows (``YAUYAU_KERNEL``, default compiled where numba is)."""
    choice = os.environ.get("YAUYAU_KERNEL", "").strip().lower() or None
    if choice is not None and choice not in KERNELS:
        raise ValueError(f"YAUYAU_KERNEL={choice!r}: expected one of {', '.join(KERNELS)}")
    if choice == "numpy":
        return False
    if choice is None:
        return _numba_installed()
    return True  # asked for: a missing numba raises ImportError on first use


def _numba_installed() -> bool:
    return importlib.util.find_spec("numba") is not None


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


def writable_cache_dir() -> Path | None:
    """:func:`cache_dir` made and checked writable, or None (compile in memory) with a warning, once."""
    path = cache_dir()
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
