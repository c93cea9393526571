"""yauyau: the optimal nonlinear filter in real time (the Yau–Yau algorithm).

The repository keeps the three layers as top-level folders (``solver/`` the mathematics,
``storage/`` files and rows, ``service/`` HTTP and the CLI); installed, they are the subpackages
``yauyau.solver``, ``yauyau.storage`` and ``yauyau.service`` (pyproject.toml's ``package-dir``), and
nothing else is put at the top level of site-packages.
"""

from __future__ import annotations

from pathlib import Path as _Path

# In a source checkout this file sits in ``yauyau/`` beside ``solver/``, ``storage/`` and
# ``service/``: the checkout's root then serves as the rest of the package (so the tests, the
# benchmarks and ``PYTHONPATH=.`` run the working tree).  Installed, the subpackages are copied
# next to this file and nothing is added.
if not (_Path(__file__).resolve().parent / "solver").is_dir():
    __path__.append(str(_Path(__file__).resolve().parent.parent))  # noqa: F821 (a package's __path__)

__version__ = "0.2.0"

# The public API, small and stable.  Loaded on first use (PEP 562) so that ``import yauyau`` and the
# CLI's start-up stay cheap: nothing below is imported until it is asked for.
_API = {
    # specs and models
    "load_spec": "yauyau.solver.spec",
    "parse_spec_text": "yauyau.solver.spec",
    "ModelSpec": "yauyau.solver.spec",
    "compile_model": "yauyau.solver.model",
    "Model": "yauyau.solver.model",
    # offline stage and the store
    "precompute": "yauyau.api",
    "ModelStore": "yauyau.storage.model_store",
    # filtering
    "open_filter": "yauyau.api",
    "load_model": "yauyau.api",
    "choose_method": "yauyau.solver.methods",
    "OnlineFilter": "yauyau.api",
    "make_filter": "yauyau.solver.methods",
    "Estimate": "yauyau.solver.filtering",
    "ChunkResult": "yauyau.solver.filtering",
    "simulate": "yauyau.api",
    # analysis
    "analyze": "yauyau.api",
    # errors (each names the field at fault)
    "YauyauError": "yauyau.solver.errors",
    "SpecError": "yauyau.solver.errors",
    "InputError": "yauyau.solver.errors",
    "StoreError": "yauyau.storage.errors",
}

# Subpackages reached as attributes after a plain ``import yauyau`` (``yauyau.examples.path(...)``).
_SUBPACKAGES = ("examples",)

__all__ = ["__version__", *_API, *_SUBPACKAGES]


def __getattr__(name: str):
    module = _API.get(name)
    if module is None and name not in _SUBPACKAGES:
        raise AttributeError(f"module 'yauyau' has no attribute {name!r}")
    import importlib

    if module is None:  # a subpackage: importing it binds it here too
        return importlib.import_module(f"yauyau.{name}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
