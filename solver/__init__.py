"""yauyau solver: the mathematics (pure numpy/scipy/SymPy; imports neither storage nor service).

The names below are loaded on first use, so importing one module of the solver does not import the
others (``yauyau.solver.spec`` needs neither the model nor SymPy).
"""

_LAZY = {"InputError": "errors", "SpecError": "errors", "YauyauError": "errors", "Model": "model",
         "compile_model": "model", "ModelSpec": "spec", "load_spec": "spec", "parse_spec_text": "spec",
         "spec_from_dict": "spec"}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
