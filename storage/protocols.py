"""What the service needs of a store: the protocols its stores implement.

``SessionStore`` — filter states advanced by numbered chunks, each applied exactly once
(:class:`storage.session_store.SqliteSessionStore`; a PostgreSQL store for several hosts implements
the same methods).  ``ModelRepository`` — precomputed models by id
(:class:`storage.model_store.ModelStore`).  A new store is one module implementing one of these
plus the line in the service that opens it.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol, runtime_checkable

# compute(state) -> (new state, response): the response a dict, or its JSON text
Compute = Callable[[dict[str, Any]], tuple[dict[str, Any], "dict[str, Any] | str"]]


@runtime_checkable
class SessionStore(Protocol):
    def create(self, model_id: str, method: str, state: dict[str, Any],
               initial_response: dict[str, Any] | None = None, options: dict[str, Any] | None = None,
               owner: str | None = None) -> str:
        """A new session at seq 0 with its ``options`` (a JSON object kept as given) and ``owner`` (the
        tenant it belongs to, or None); returns its id."""

    def get(self, session_id: str) -> Any:
        """The session's record (id, model_id, method, state, next_seq, options, ...; ``options`` is
        ``{}`` for a session stored without); NotFound if absent."""

    def apply_chunk(self, session_id: str, seq: int, compute: Compute,
                    encoded: bool = False, digest: str | None = None) -> tuple[Any, bool]:
        """Apply chunk ``seq`` exactly once: (response, replayed).  A seq past the next one is a
        Conflict and changes nothing; a seq already applied returns the stored response, or is a
        Conflict when its ``digest`` (of the request) differs from the stored one.  Any numbered
        operation on a session goes through here (a chunk of rows, a reset), one seq each."""

    def apply_chunks(self, requests: list[tuple[str, int, str | None]], compute_many: Any,
                     encoded: bool = False, records: list[Any] | None = None) -> list[Any]:
        """Chunks (session id, seq, digest) of different sessions, each exactly as apply_chunk would
        apply it, computed by one ``compute_many([(index, state)])`` call and stored together:
        [(response, replayed) or that chunk's exception]."""

    def delete(self, session_id: str) -> None:
        """Remove the session; NotFound if absent."""


@runtime_checkable
class ModelRepository(Protocol):
    def ids(self) -> list[str]:
        """The stored model ids."""

    def exists(self, model_id: str) -> bool: ...

    def load(self, model_id: str) -> Any:
        """The verified stored model (spec_json, arrays, attrs); StoreError if unreadable."""

    def list(self) -> list[Any]:
        """Summaries from metadata only (no arrays read)."""
