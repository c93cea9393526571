"""The models a worker serves: listed from the store's file attributes at start-up, loaded on first
use and kept in a bounded least-recently-used cache.

A model's summary (``GET /v1/models``, ``GET /v1/models/{id}``) is the one stored in its file at
precompute (storage/model_store.py), read by :func:`listing`, never computed again here.

Start-up reads no arrays and runs no analysis, so a server is ready at once whatever the number of
stored models.  A model is loaded (verified, compiled, its offline arrays and default filter built)
by the first request that needs it; the filter method is the one chosen at precompute
(:func:`yauyau.api.load_model`).  At most ``capacity`` models stay in memory; the least recently
used one is dropped (a session of a dropped model is served by loading it again).
"""

from __future__ import annotations

import gc
import json
import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from yauyau.solver.filtering import Filter
from yauyau.storage.errors import NotFound, StoreError
from yauyau.storage.model_store import SUMMARY_FIELDS, ModelStore, ModelSummary

from yauyau.api import load_model as load_stored

log = logging.getLogger("yauyau.service")
FILTER_VARIANTS = 16  # (method, gate) filters kept per loaded model: sessions may choose their gate


def listing(summary: ModelSummary) -> dict[str, Any]:
    """A model as ``GET /v1/models`` lists it: its stored summary and the method chosen at precompute;
    an unreadable file: its id and the error."""
    if summary.error is not None:
        return {"id": summary.id, "error": summary.error}
    fields = summary.to_dict()
    return {"id": summary.id, **{key: fields[key] for key in SUMMARY_FIELDS},
            "method": summary.extra.get("method")}


@dataclass
class LoadedModel:
    id: str
    spec: dict[str, Any]
    model: Any
    offline: Any
    listed: dict[str, Any]  # as GET /v1/models lists it (:func:`listing`)
    method: str  # chosen at precompute
    filters: OrderedDict[tuple[str, float | None], Filter] = field(default_factory=OrderedDict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def filter(self, method: str | None = None, gate: float | None = None) -> Filter:
        """The filter for ``method`` (None: the one chosen at precompute) with the outlier ``gate``
        (None: the spec's), built once per method and shared by all sessions of this worker; another
        gate is a shallow copy sharing the method's arrays (``with_gate``).  At most
        ``FILTER_VARIANTS`` (method, gate) pairs are kept (least recently used dropped first)."""
        key = (method or self.method, None if gate is None else float(gate))
        with self._lock:
            flt = self.filters.get(key)
            if flt is None:
                base = self.filters.get((key[0], None))
                if base is None:
                    from yauyau.solver.methods import make_filter

                    base = self.filters[(key[0], None)] = make_filter(self.model, self.offline, key[0])
                flt = self.filters[key] = base if key[1] is None else base.with_gate(key[1])
                while len(self.filters) > FILTER_VARIANTS:
                    self.filters.popitem(last=False)
            else:
                self.filters.move_to_end(key)
            return flt

    def summary(self) -> dict[str, Any]:
        """The model as ``GET /v1/models`` lists it (its stored summary)."""
        return dict(self.listed)


def load_model(store: ModelStore, model_id: str) -> LoadedModel:
    stored = load_stored(store, model_id)
    summary = store.summary(model_id)
    if summary.error is not None:  # the file changed since it was loaded a moment ago
        raise StoreError("model", f"model file {model_id}: {summary.error}")
    spec_doc = json.loads(stored.model.spec.canonical_json())
    loaded = LoadedModel(id=model_id, spec=spec_doc, model=stored.model, offline=stored.offline,
                         listed=listing(summary), method=stored.method)
    loaded.filter()  # the default filter now, not inside the first chunk
    return loaded


class Registry:
    """The models of one store directory, by id, loaded on demand (LRU of ``capacity`` models)."""

    def __init__(self, store: ModelStore, capacity: int = 8):
        self.store = store
        self.capacity = max(1, int(capacity))
        self._cache: OrderedDict[str, LoadedModel] = OrderedDict()
        self._lock = threading.Lock()
        self._loading: dict[str, threading.Lock] = {}
        self.loads = 0  # models loaded so far (a reload after eviction counts again)

    @classmethod
    def open(cls, directory: Path, capacity: int = 8) -> "Registry":
        registry = cls(ModelStore(directory), capacity)
        log.info("model store %s: %d model(s), loaded on first use (cache of %d)", directory,
                 len(registry.store.ids()), registry.capacity)
        return registry

    def ids(self) -> list[str]:
        return self.store.ids()

    def loaded_ids(self) -> list[str]:
        with self._lock:
            return list(self._cache)

    def summaries(self) -> list[dict[str, Any]]:
        """Every stored model, from the file attributes (no arrays read); unreadable files are listed
        with their error instead of a summary."""
        return [listing(summary) for summary in self.store.list()]

    def get(self, model_id: str, field_name: str = "model") -> LoadedModel:
        with self._lock:
            loaded = self._cache.get(model_id)
            if loaded is not None:
                self._cache.move_to_end(model_id)
                return loaded
            if not self.store.exists(model_id):
                raise NotFound(field_name, f"no model {model_id!r} (see GET /v1/models)")
            gate = self._loading.setdefault(model_id, threading.Lock())
        with gate:  # one load per model at a time; others wait for it
            with self._lock:
                if model_id in self._cache:
                    self._cache.move_to_end(model_id)
                    return self._cache[model_id]
            loaded = load_model(self.store, model_id)
            with self._lock:
                self.loads += 1
                self._cache[model_id] = loaded
                while len(self._cache) > self.capacity:
                    dropped, _ = self._cache.popitem(last=False)
                    log.info("model %s dropped from the cache (capacity %d)", dropped, self.capacity)
                self._loading.pop(model_id, None)
            log.info("loaded model %s (%s, method %s)", model_id, loaded.model.spec.name, loaded.method)
            gc.freeze()  # the model's objects live long: out of the collector's scans (app.py)
            return loaded
