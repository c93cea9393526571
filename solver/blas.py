"""How many BLAS threads the online products use: one per process unless asked otherwise.

Each step of the engine is two matrix-vector products of a few MB; split over threads they pay a
hand-off per product, and when another process holds a core the split waits for it (measured:
bench/results/blas.md).  So the library, the CLI and the service all run them with one BLAS thread by
default: ``blas_threads=`` / ``--blas-threads`` / ``YAUYAU_BLAS_THREADS`` raise it (0 in the library:
leave BLAS as the process has it).  threadpoolctl sets it.
"""

from __future__ import annotations

import os
from typing import Any

from .errors import InputError

ENV = "YAUYAU_BLAS_THREADS"
MAX_THREADS = 1024


def blas_threads(requested: int | None, *, allow_keep: bool = False) -> int:
    """The BLAS thread count: ``requested``, else $YAUYAU_BLAS_THREADS, else 1 (``allow_keep``: 0 is
    accepted and means "leave BLAS as it is")."""
    field = "blas_threads"
    if requested is None:
        text = os.environ.get(ENV, "1")
        try:
            requested = int(text)
        except ValueError:
            raise InputError(ENV, f"must be a positive integer, got {text!r}") from None
        field = ENV
    if isinstance(requested, bool) or not isinstance(requested, int):
        raise InputError(field, f"must be a positive integer, got {requested!r}")
    low = 0 if allow_keep else 1
    if not low <= requested <= MAX_THREADS:
        keep = " or 0 (leave BLAS as it is)" if allow_keep else ""
        raise InputError(field, f"must be a positive integer (at most {MAX_THREADS}){keep}, got {requested}")
    return requested


def limit_process_blas(threads: int) -> None:
    """Limit every BLAS library loaded in this process to ``threads`` threads, for good (0: nothing)."""
    if threads:
        limited_blas(threads)


def limited_blas(threads: int) -> Any:
    """threadpoolctl's limit of every BLAS library to ``threads`` (a context manager; left unused, for
    good).  scipy's own BLAS (scipy.linalg.blas and cython_blas: the engine's products, numpy path and
    compiled kernels) is a library apart from numpy's, loaded on its first import: it is loaded here
    first, or a process limited before its first model (the service's workers) ran the products on
    every core."""
    import scipy.linalg.blas  # noqa: F401 - loads scipy's BLAS library, so that it is limited too
    from threadpoolctl import threadpool_limits  # lazy: it inspects the loaded libraries (~3 ms)

    return threadpool_limits(limits=threads, user_api="blas")
