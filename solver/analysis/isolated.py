"""The analysis in a process of its own, killed at its time limit plus a grace period.

The analysis (SymPy) is bounded from inside (:mod:`.budget`: a deadline checked between steps, every
expand sized before it starts), but one SymPy call cannot be interrupted (an ``sp.simplify`` of nested
trigonometric functions runs for minutes) and it holds the GIL of the process it runs in.  So every
caller that promises a time limit — ``yauyau analyze``, ``yauyau precompute`` / :func:`yauyau.precompute`
with method auto, the precompute jobs of ``POST /v1/models``, ``POST /v1/analyze`` — runs it here: a
child process that is killed (SIGKILL) ``grace`` seconds after its limit.  The caller then gets the
report the analysis gives when its own deadline stops it (:func:`.report.stopped_report`): the
conditions the child had decided before (it sends them before building the estimation algebra), every
other one undecided within the time limit, the recommendation from those (the general engine, method
yau-yau, which is always valid, when nothing was decided), and a note saying that the process was
stopped.

How the child starts (``start``):

* ``"auto"`` (the default, for the CLI and library users): a fork of the caller when it runs no other
  thread (a fork of a threaded process can deadlock in the child), else ``"subprocess"``;
* ``"subprocess"``: ``python -m yauyau.solver.analysis.isolated FD``.  Neither re-imports the caller's
  ``__main__`` (a script without an ``if __name__ == "__main__"`` guard stays safe).  Their start-up
  (imports: SymPy, ~1 s for a fresh Python) is not counted in the limit; it is bounded by
  :data:`STARTUP_LIMIT`;
* ``"forkserver"`` (a server): a fork of a process that has SymPy and the analysis loaded (~20 ms).

The child also caps its own CPU time (limit + grace + start-up), so that it dies even if its parent is
killed first.  Messages (pickled lists) go from child to parent over a pipe:
``["ready"]``, ``["conditions", facts]``, then one of ``["report", dict, text]``,
``["spec", field, message]`` or ``["error", text]``.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from ..errors import SpecError

if TYPE_CHECKING:  # types only
    from ..model import Model
    from ..spec import ModelSpec

DEFAULT_GRACE = 2.0  # seconds past the time limit before the analysis process is killed
STARTUP_LIMIT = 60.0  # seconds a child may take to start (its imports: SymPy) before it is killed
_PRELOAD = ["yauyau.solver.analysis", "yauyau.solver.model", "yauyau.solver.spec"]


class AnalysisBusy(Exception):
    """Every analysis slot stayed busy for the request's time limit."""


@dataclass(frozen=True)
class Analysis:
    """An analysis run in a child process: its report as a dict (``AnalysisReport.to_dict()``) and as
    text (``render()``); ``stopped`` when the child was killed (or died) and the report is the bounded
    one built from what it had decided."""

    report: dict[str, Any]
    text: str
    stopped: bool = False

    @property
    def method(self) -> str:
        return self.report["recommendation"]["method"]

    @property
    def reason(self) -> str:
        return self.report["recommendation"]["reason"]


# -- the child ------------------------------------------------------------------------------------------
def work(spec_doc: dict[str, Any], time_limit: float, bounds: dict[str, Any], send: Callable) -> None:
    """Run in the child: compile the spec, send the decided conditions, then the report (or the spec
    error, or the failure)."""
    from ..model import compile_model
    from ..spec import spec_from_dict
    from .report import analyze

    try:
        model = compile_model(spec_from_dict(spec_doc))
        report = analyze(model, time_limit=time_limit, **bounds,
                         on_conditions=lambda facts: send(["conditions", facts.decided()]))
        send(["report", report.to_dict(), report.render()])
    except SpecError as exc:
        send(["spec", exc.field, exc.message])
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        send(["error", f"{type(exc).__name__}: {exc}"])


def _cap_cpu(seconds: float) -> None:
    """Kill this process (SIGXCPU) after ``seconds`` of CPU time, and let it write no core file: the
    backstop when the parent that should kill it was killed first."""
    import resource

    limit = max(1, math.ceil(seconds))
    try:
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        _, hard = resource.getrlimit(resource.RLIMIT_CPU)
        if hard == resource.RLIM_INFINITY or hard > limit:
            resource.setrlimit(resource.RLIMIT_CPU, (limit, limit))
    except (ValueError, OSError):
        pass  # a platform without these limits: the parent's kill still holds


def _child(conn: Connection, spec_doc: dict[str, Any], time_limit: float, bounds: dict[str, Any],
           grace: float) -> None:
    """A forked child (``"auto"`` or ``"forkserver"``): the imports (none left after a forkserver's
    preload), "ready", then the analysis."""
    _cap_cpu(time_limit + grace + STARTUP_LIMIT)
    try:
        import yauyau.solver.analysis  # noqa: F401 - the start-up, not counted in the limit

        conn.send(["ready"])
        work(spec_doc, time_limit, bounds, conn.send)
    finally:
        conn.close()


def main(argv: list[str]) -> int:
    """``python -m yauyau.solver.analysis.isolated FD``: the request (JSON) on stdin, messages on FD."""
    conn = Connection(int(argv[0]))
    request = json.loads(sys.stdin.read())
    _cap_cpu(request["time_limit"] + request["grace"] + STARTUP_LIMIT)
    try:
        import yauyau.solver.analysis  # noqa: F401 - the imports are the start-up, not the analysis

        conn.send(["ready"])
        work(request["spec"], request["time_limit"], request["bounds"], conn.send)
    finally:
        conn.close()
    return 0


# -- the parent -----------------------------------------------------------------------------------------
class AnalysisRunner:
    """Analyses in killable child processes, at most ``concurrency`` at a time (None: no limit).

    :meth:`run` returns an :class:`Analysis` within the time limit plus ``grace`` (plus the start-up of a
    ``"subprocess"`` child); a bad spec raises SpecError; a failure of the analysis RuntimeError; a
    request that finds every slot busy for its whole time limit AnalysisBusy.  ``target(conn, spec,
    time_limit, bounds, grace)`` replaces the child's work (tests: a child that never answers)."""

    def __init__(self, concurrency: int | None = None, grace: float = DEFAULT_GRACE,
                 start: str = "auto", target: Callable | None = None):
        if start not in ("auto", "subprocess", "forkserver"):
            raise ValueError(f"start must be 'auto', 'subprocess' or 'forkserver', got {start!r}")
        self.grace, self.start = grace, start
        self._target = target or _child
        self._slots = None if concurrency is None else threading.BoundedSemaphore(concurrency)
        if start == "forkserver":
            self._context = multiprocessing.get_context("forkserver")
            self._context.set_forkserver_preload(_PRELOAD)

    def warm(self) -> None:
        """Start the forkserver now (it imports SymPy and the analysis: seconds), so that the first
        :meth:`run` does not pay it inside its time limit; nothing for the other starts."""
        if self.start == "forkserver":
            from multiprocessing import forkserver

            forkserver.ensure_running()

    def run(self, spec_doc: dict[str, Any], time_limit: float, **bounds: Any) -> Analysis:
        if self._slots is not None and not self._slots.acquire(timeout=time_limit):
            raise AnalysisBusy(f"all analysis slots stayed busy for {time_limit:g} s")
        try:
            started = time.monotonic()
            messages, ended = self._messages(spec_doc, time_limit, bounds)
            return self._settle(spec_doc, time_limit, bounds, messages, ended, time.monotonic() - started)
        finally:
            if self._slots is not None:
                self._slots.release()

    def _messages(self, spec_doc: dict[str, Any], time_limit: float,
                  bounds: dict[str, Any]) -> tuple[list[list[Any]], str | None]:
        """The child's messages up to its final one, and why it ended without one (None if it did not)."""
        receive, send = multiprocessing.Pipe(duplex=False)
        child = None
        start = self.start
        if start == "auto":
            start = "fork" if threading.active_count() == 1 else "subprocess"
        try:
            if start == "subprocess":
                child = _SubprocessChild(send, spec_doc, time_limit, bounds, self.grace)
            else:
                context = self._context if start == "forkserver" else multiprocessing.get_context("fork")
                child = _ForkedChild(context, self._target, send, spec_doc, time_limit, bounds, self.grace)
            send.close()  # the child holds the other end: its death is an EOF here
            if start != "forkserver":  # a forkserver's child is ready when it starts: its imports are done
                first, why = _receive(receive, time.monotonic() + STARTUP_LIMIT)
                if first is None:
                    why = why if why != "timeout" else f"did not start within {STARTUP_LIMIT:g} s"
                    return [], why
                if first[0] != "ready":  # a final answer already (nothing else comes before "ready")
                    return [first], None
            return _collect(receive, time.monotonic() + time_limit + self.grace, time_limit, self.grace)
        finally:
            receive.close()
            if child is not None:
                child.stop()

    def _settle(self, spec_doc: dict[str, Any], time_limit: float, bounds: dict[str, Any],
                messages: list[list[Any]], ended: str | None, elapsed: float) -> Analysis:
        from ..model import compile_model
        from ..spec import spec_from_dict
        from .conditions import Facts
        from .report import stopped_report

        if ended is None:
            final = messages[-1]
            if final[0] == "report":
                return Analysis(final[1], final[2])
            if final[0] == "spec":
                raise SpecError(final[1], final[2])
            raise RuntimeError(f"analysis failed: {final[1]}")
        decided = [m[1] for m in messages if m[0] == "conditions"]
        facts = Facts.from_decided(decided[-1]) if decided else None
        report = stopped_report(compile_model(spec_from_dict(spec_doc)), facts, time_limit,
                                f"the analysis process {ended} and was stopped: what it had not decided by "
                                "then is reported undecided", **bounds)
        report.elapsed = elapsed
        return Analysis(report.to_dict(), report.render(), stopped=True)


def _receive(conn: Connection, deadline: float) -> tuple[list[Any] | None, str]:
    """One message before ``deadline``, or (None, why: "timeout" or how the child ended)."""
    remaining = deadline - time.monotonic()
    try:
        if remaining <= 0 or not conn.poll(remaining):
            return None, "timeout"
        return conn.recv(), ""
    except (EOFError, OSError):
        return None, "ended without a report"


def _collect(conn: Connection, deadline: float, time_limit: float,
             grace: float) -> tuple[list[list[Any]], str | None]:
    messages: list[list[Any]] = []
    while True:
        message, why = _receive(conn, deadline)
        if message is None:
            if why == "timeout":
                why = f"did not finish within its time limit of {time_limit:g} s (+{grace:g} s grace)"
            return messages, why
        if message[0] != "ready":
            messages.append(message)
        if message[0] not in ("ready", "conditions"):
            return messages, None


class _ForkedChild:
    def __init__(self, context, target: Callable, send: Connection, spec_doc: dict[str, Any],
                 time_limit: float, bounds: dict[str, Any], grace: float):
        for stream in (sys.stdout, sys.stderr):  # a fork copies unwritten output, and the child flushes it
            try:
                stream.flush()
            except (AttributeError, OSError, ValueError):
                pass
        self.process = context.Process(target=target, args=(send, spec_doc, time_limit, bounds, grace),
                                       daemon=True, name="yauyau-analysis")
        self.process.start()

    def stop(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=5)


class _SubprocessChild:
    def __init__(self, send: Connection, spec_doc: dict[str, Any], time_limit: float,
                 bounds: dict[str, Any], grace: float):
        import yauyau

        fd = send.fileno()
        env = dict(os.environ)
        home = str(Path(yauyau.__file__).resolve().parents[1])  # where this yauyau is imported from
        env["PYTHONPATH"] = os.pathsep.join(p for p in (home, env.get("PYTHONPATH")) if p)
        self.process = subprocess.Popen(
            [sys.executable, "-m", "yauyau.solver.analysis.isolated", str(fd)], pass_fds=(fd,), env=env,
            stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        request = {"spec": spec_doc, "time_limit": time_limit, "grace": grace, "bounds": bounds}
        try:
            self.process.stdin.write(json.dumps(request).encode())
            self.process.stdin.close()
        except OSError:
            pass  # it died at once: the pipe says so (EOF)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        try:
            self.process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass


_ONE_SHOT = AnalysisRunner()


def analyze_isolated(model: Model | ModelSpec, time_limit: float, *, grace: float = DEFAULT_GRACE,
                     **bounds: Any) -> Analysis:
    """:func:`analyze` of ``model`` (a compiled Model or a ModelSpec) in a child process killed
    ``grace`` seconds after ``time_limit``: the report (or the bounded one) within that, plus the
    child's start-up."""
    spec = getattr(model, "spec", model)
    runner = _ONE_SHOT if grace == DEFAULT_GRACE else AnalysisRunner(grace=grace)
    return runner.run(json.loads(spec.canonical_json()), time_limit, **bounds)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
