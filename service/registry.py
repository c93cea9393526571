"""The models a worker serves, loaded once at start-up and kept in memory.

Each stored model becomes a compiled :class:`solver.model.Model`, its
:class:`solver.offline.OfflineModel` (the propagators) and one filter per method asked for.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from yauyau.solver.filtering import Filter
from yauyau.solver.model import Model, compile_model
from yauyau.solver.spec import spec_from_dict
from yauyau.storage.errors import NotFound
from yauyau.storage.model_store import ModelStore

log = logging.getLogger("yauyau.service")


@dataclass
class LoadedModel:
    id: str
    spec: dict[str, Any]
    model: Model
    offline: Any
    basis: int
    filters: dict[str, Filter] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def filter(self, method: str | None = None) -> Filter:
        """The filter for ``method`` (None: the spec's), built once and shared by all sessions."""
        key = method or self.model.spec.method
        with self._lock:
            if key not in self.filters:
                from yauyau.solver.methods import make_filter

                self.filters[key] = make_filter(self.model, self.offline, key)
            return self.filters[key]

    def summary(self) -> dict[str, Any]:
        spec = self.model.spec
        return {"id": self.id, "name": spec.name, "state": list(spec.state), "n": spec.n, "m": spec.m,
                "dt": spec.discretization.dt, "radius": spec.domain.radius, "basis": self.basis,
                "method": self.filter().method}


def load_model(store: ModelStore, model_id: str) -> LoadedModel:
    from yauyau.solver.offline import OfflineModel

    stored = store.load(model_id)
    spec_doc = json.loads(stored.spec_json)
    model = compile_model(spec_from_dict(spec_doc))
    offline = OfflineModel.from_arrays(model, stored.arrays)
    arrays = stored.arrays
    basis = arrays["basis"].shape[-1] if "basis" in arrays else spec_doc["discretization"]["basis"]
    loaded = LoadedModel(id=model_id, spec=spec_doc, model=model, offline=offline, basis=int(basis))
    loaded.filter()  # build the default filter now, not on the first request
    return loaded


class Registry:
    """Every model of the store directory, by id (unreadable ones are logged and skipped)."""

    def __init__(self, models: dict[str, LoadedModel]):
        self.models = models

    @classmethod
    def load(cls, directory: Path) -> "Registry":
        store = ModelStore(directory)
        models = {}
        for model_id in store.ids():
            try:
                models[model_id] = load_model(store, model_id)
            except Exception as exc:  # one bad file must not take the service down
                log.error("skipping model %s: %s", model_id, exc)
        log.info("loaded %d model(s) from %s", len(models), directory)
        return cls(models)

    def get(self, model_id: str, field_name: str = "model") -> LoadedModel:
        try:
            return self.models[model_id]
        except KeyError:
            raise NotFound(field_name, f"no model {model_id!r} (see GET /v1/models)") from None
