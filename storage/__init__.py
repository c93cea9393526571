"""yauyau storage: files, not math (never imports solver or service).

``ModelStore`` — HDF5 files of precomputed models named by the hash of their spec;
``SqliteSessionStore`` — SQLite sessions whose chunks are applied exactly once; the protocols the
service programs against (``SessionStore``, ``ModelRepository``) are in ``storage.protocols``.
The stores are imported lazily so that ``storage.errors`` stays cheap to import.
"""

from .errors import Conflict, NotFound, StoreError

_LAZY = {"ModelStore": "model_store", "StoredModel": "model_store", "ModelSummary": "model_store",
         "model_id": "model_store", "SqliteSessionStore": "session_store", "SessionRecord": "session_store",
         "SessionStore": "protocols", "ModelRepository": "protocols"}

__all__ = ["Conflict", "NotFound", "StoreError", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
