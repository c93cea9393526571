"""The online Yau–Yau engine (seed 002 §5): the filter, its kernel and loops, its state, many states
stepped together (batch), a ball that follows the state (follow, recentring, frame, atlas), the flow
over irregular gaps (semigroup) and the degeneracy diagnostics.

``from yauyau.solver.engine import YauYauFilter`` works; the name is loaded on first use, so importing
one module of the room does not import the others.
"""

_LAZY = {"YauYauFilter": "filter", "build": "filter", "YauYauState": "state"}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib  # lazy: the room's modules load on first use (start-up cost of the CLI)

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
