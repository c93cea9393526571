"""POST /v1/analyze in a process of its own, with a hard deadline.

The analysis (SymPy) is bounded from inside (solver/analysis/budget.py: a deadline checked between
steps, and every expand sized before it starts), but one SymPy call cannot be interrupted and it
holds the GIL of the process it runs in.  So a server never runs it in its own process: each request
forks a child from a forkserver that has SymPy and the analysis loaded (~20 ms), waits for the report
at most ``time_limit + grace`` seconds and then kills it (SIGKILL).  At most ``concurrency`` analyses
run per worker; a request that finds them all busy waits for a slot no longer than its own limit and
then gets 503 with Retry-After.  The chunk path never waits on an analysis.
"""

from __future__ import annotations

import multiprocessing
import threading
from typing import Any

from yauyau.solver.errors import SpecError

_PRELOAD = ["yauyau.solver.analysis", "yauyau.solver.model", "yauyau.solver.spec"]


class AnalysisBusy(Exception):
    """Every analysis slot of this worker stayed busy for the request's time limit."""


class AnalysisTimedOut(Exception):
    """The analysis process did not answer within its limit plus the grace period (it was killed)."""


def _child(conn, spec: dict[str, Any], time_limit: float) -> None:
    from yauyau.solver.analysis import analyze
    from yauyau.solver.model import compile_model
    from yauyau.solver.spec import spec_from_dict

    try:
        report = analyze(compile_model(spec_from_dict(spec)), time_limit=time_limit)
        conn.send(("ok", report.to_dict()))
    except SpecError as exc:
        conn.send(("spec", exc.field, exc.message))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which logs it
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


class AnalysisRunner:
    """Analyses in killable child processes, ``concurrency`` at a time."""

    def __init__(self, concurrency: int = 1, grace: float = 2.0, target=None):
        self.grace = grace
        self._target = target or _child  # (conn, spec, time_limit) -> None, run in the child
        self._slots = threading.BoundedSemaphore(concurrency)
        self._context = multiprocessing.get_context("forkserver")
        self._context.set_forkserver_preload(_PRELOAD)

    def run(self, spec: dict[str, Any], time_limit: float) -> dict[str, Any]:
        """The report as a dict; SpecError for a bad spec; AnalysisBusy / AnalysisTimedOut."""
        if not self._slots.acquire(timeout=time_limit):
            raise AnalysisBusy(f"all analysis slots stayed busy for {time_limit:g} s")
        try:
            return self._run(spec, time_limit)
        finally:
            self._slots.release()

    def _run(self, spec: dict[str, Any], time_limit: float) -> dict[str, Any]:
        receive, send = self._context.Pipe(duplex=False)
        process = self._context.Process(target=self._target, args=(send, spec, time_limit), daemon=True,
                                        name="yauyau-analysis")
        process.start()
        send.close()
        try:
            if not receive.poll(time_limit + self.grace):
                raise AnalysisTimedOut(f"the analysis did not finish within {time_limit:g} s "
                                       f"(+{self.grace:g} s grace) and was stopped")
            try:
                result = receive.recv()
            except EOFError:  # the child died without answering (killed, out of memory)
                raise AnalysisTimedOut("the analysis process ended without a report") from None
        finally:
            receive.close()
            if process.is_alive():
                process.kill()
            process.join(timeout=5)
        if result[0] == "spec":
            raise SpecError(result[1], result[2])
        if result[0] == "error":
            raise RuntimeError(f"analysis failed: {result[1]}")
        return result[1]


_RUNNER_LOCK = threading.Lock()


def analysis_runner(app) -> AnalysisRunner:
    """The application's runner, made on first use (app.state.analysis)."""
    with _RUNNER_LOCK:
        runner = getattr(app.state, "analysis", None)
        if runner is None:
            settings = app.state.settings
            runner = AnalysisRunner(settings.analyze_concurrency, settings.analyze_grace)
            app.state.analysis = runner
        return runner
