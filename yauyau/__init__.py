"""The optimal nonlinear filter in real time: the Yau–Yau algorithm (:mod:`yauyau`)
=================================================================================

.. currentmodule:: yauyau

yauyau estimates the hidden state x(t) of dx = f(x) dt + G dv from observations dy = h(x) dt + dw
(or from readings z = h(x) + v at any times) with the conditional density itself, not a
linearisation.  A model is a spec file, TOML or JSON (docs/models.md).  Its offline stage is solved
once and stored (an HDF5 file per model in a store directory); a filter opened on the stored model
then takes the observations as they arrive and gives the conditional mean, covariance, mode,
quantiles and density after each.  The names below are ``yauyau.__all__``; each is imported on
first use, so ``import yauyau`` is cheap.

Specs and models
----------------

.. autosummary::

   load_spec        -- read a spec file (.toml or .json) into a ModelSpec
   parse_spec_text  -- the same from TOML or JSON text
   ModelSpec        -- a validated spec: signal, sensor, noises, prior, domain, discretisation
   compile_model    -- the Model of a spec: f, h and the prior as numpy functions (no SymPy)
   Model            -- a compiled model, what simulate, analyze and make_filter take
   precompute       -- solve the offline stage once, choose the method, store both; returns the model id
   ModelStore       -- a directory of stored models, one <id>.h5 file each
   load_model       -- read and verify a stored model: compiled model, offline arrays, method
   examples         -- the example specs shipped with the package: examples.path("cubic_sensor"),
                       examples.names()

Filtering
---------

.. autosummary::

   open_filter      -- an OnlineFilter of a stored model, with the method chosen at precompute
   OnlineFilter     -- a filter and its state: step, run, predict, density, marginal, quantiles,
                       mode, state_dict and restore, reset, reinitialise
   Estimate         -- one step: mean, cov, mode, loglik, predictive_loglik, gated, degenerate, reason
   ChunkResult      -- a chunk's estimates as arrays, what OnlineFilter.run returns
   choose_method    -- the method for a model and why (auto: the estimation-algebra analysis)
   make_filter      -- a filter of a compiled model by method name: yau-yau, kalman-bucy, yau-hu,
                       yau-jia, wei-norman

Simulation and checks
---------------------

.. autosummary::

   simulate         -- a true path and its rows (increments dy or readings z), every dt or at given times

Fitting
-------

.. autosummary::

   fit              -- maximum-likelihood estimates of a spec's parameters and noise levels from a
                       record, with standard errors (the filter's own log-likelihood)
   FitResult        -- estimates, stderr, loglik, evaluations, converged, method, profile, fitted spec

Before any data, ``yauyau check SPEC`` (the command line) filters a few simulated paths against a
reference (the exact Kalman filter, or the engine at twice the basis) and says whether the spec's
discretisation resolves the posterior.

Analysis
--------

.. autosummary::

   analyze          -- Wong matrix, estimation algebra and the recommended method of a spec (a file,
                       a ModelSpec) or a compiled model

Errors, each naming the field at fault (``.field``)
---------------------------------------------------

.. autosummary::

   YauyauError      -- the base of SpecError and InputError: errors that are the user's to fix
   SpecError        -- a spec, or an argument derived from one, is invalid
   InputError       -- bad online input: increments, readings, times, points
   StoreError       -- a stored model or session is missing, corrupt or mismatched

``__version__`` is the version of the package.

Example, from any directory (the example specs ship with the package)::

    import yauyau
    spec = yauyau.load_spec(yauyau.examples.path("cubic_sensor"))
    flt = yauyau.open_filter("var/store", yauyau.precompute(spec, "var/store"))
    sim = yauyau.simulate(spec, steps=1000, seed=1)        # a true path and its increments dy
    chunk = flt.run(sim.increments)                        # chunk.mean (1000, 1), chunk.cov (1000, 1, 1)
    print(flt.method, chunk.mean[-1], flt.quantiles([0.05, 0.5, 0.95]))

Below these names: ``yauyau.solver`` (the mathematics, no I/O), ``yauyau.storage`` (model files and
session stores) and ``yauyau.service`` (the command line and the HTTP API); docs/architecture.md says
how they fit.
"""

from __future__ import annotations

from pathlib import Path as _Path
from typing import Any

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
    # fitting
    "fit": "yauyau.solver.fitting",
    "FitResult": "yauyau.solver.fitting",
    # errors (each names the field at fault)
    "YauyauError": "yauyau.solver.errors",
    "SpecError": "yauyau.solver.errors",
    "InputError": "yauyau.solver.errors",
    "StoreError": "yauyau.storage.errors",
}

# Subpackages reached as attributes after a plain ``import yauyau`` (``yauyau.examples.path(...)``).
_SUBPACKAGES = ("examples",)

__all__ = ["__version__", *_API, *_SUBPACKAGES]


def __getattr__(name: str) -> Any:
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
