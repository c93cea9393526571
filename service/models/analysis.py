"""POST /v1/analyze in a process of its own, with a hard deadline.

The runner itself is the solver's (yauyau.solver.analysis.isolated, which ``yauyau analyze``, precompute
and the precompute jobs use too): here it forks each analysis from a forkserver that has SymPy and the
analysis loaded (~20 ms; the forkserver itself starts with the application, in the background:
:func:`warm_analysis`), kills it ``analyze_grace`` seconds after its time limit and answers the
bounded report (what was not decided by then undecided, the general engine recommended unless the
conditions it decided say otherwise).  At most ``analyze_concurrency`` analyses run per worker; a
request that finds them all busy waits for a slot no longer than its own limit and then gets 503 with
Retry-After.  The chunk path never waits on an analysis.
"""

from __future__ import annotations

import gc
import threading

from yauyau.solver.analysis.isolated import AnalysisBusy, AnalysisRunner
from yauyau.solver.warm import warm_kernels

__all__ = ["AnalysisBusy", "AnalysisRunner", "analysis_runner", "warm_analysis"]

_RUNNER_LOCK = threading.Lock()


def warm_analysis(app) -> threading.Thread:
    """In the background (a daemon thread): make the application's runner and start its forkserver, so
    the first POST /v1/analyze is answered within its limit plus grace like the others, not after the
    forkserver's imports; then make the engine's compiled row loops ready (solver/warm.py: about 0.5-2 s
    with numba's cache filled, which ``yauyau precompute`` does), so no chunk compiles them.  Readiness
    does not wait for it: a chunk in the first seconds after start-up may."""
    def warm() -> None:
        analysis_runner(app).warm()
        warm_kernels()  # the engine's compiled row loops: numba's import and cache, not in a chunk
        # numba's modules and the compiled loops live as long as the process: out of the cyclic
        # collector's scans like the start-up's (app.py), which froze before they were imported
        gc.freeze()

    thread = threading.Thread(target=warm, name="warm-up", daemon=True)
    thread.start()
    return thread


def analysis_runner(app) -> AnalysisRunner:
    """The application's runner, made on first use (app.state.analysis)."""
    with _RUNNER_LOCK:
        runner = getattr(app.state, "analysis", None)
        if runner is None:
            settings = app.state.settings
            runner = AnalysisRunner(settings.analyze_concurrency, settings.analyze_grace, start="forkserver")
            app.state.analysis = runner
        return runner
