"""Micro-batching: the chunks that wait together are applied together.

One thread applies every numbered operation of a worker process (a chunk, a reset) in arrival
order — first come, first served, and the event loop stays free to read the next requests.  While it
computes, new chunks queue up; it then takes all of them at once (up to ``max_batch``, and after
waiting ``window`` seconds more for stragglers when a window is set) and hands them to
``Sessions.observe_many``, which steps the chunks of one model together (one matrix product per step
for all of them) and stores them in one transaction.  Each chunk keeps its own seq and its own answer:
one that fails gets its own error, the others are unaffected.  Two chunks of one session never share
a batch (the later one goes in the next), so a client that pipelines seq n and n + 1 gets both
applied in order.  Anything else submitted (a reset) runs alone, in its place in the order.
"""

from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Executor, Future
from typing import Any, Callable

from .. import metrics

_STOP = object()


class ChunkBatcher(Executor):
    """An executor of one thread whose chunks (:meth:`submit_chunk`) are applied in batches by
    ``apply_many(requests) -> [answer or exception]``; plain :meth:`submit` calls run alone."""

    def __init__(self, apply_many: Callable[[list[Any]], list[Any]], window: float = 0.0,
                 max_batch: int = 256):
        self.apply_many = apply_many
        self.window = float(window)
        self.max_batch = int(max_batch)
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._closed = False
        self._closing = threading.Lock()  # a submit never lands behind the stop
        self._held: list[tuple] = []  # taken from the queue but left for the next batch (same session)
        self._thread = threading.Thread(target=self._loop, name="yauyau-chunk", daemon=True)
        self._thread.start()

    def submit(self, fn: Callable, /, *args: Any, **kwargs: Any) -> Future:
        return self._put(("call", lambda: fn(*args, **kwargs)))

    def submit_chunk(self, request: Any) -> Future:
        """Apply ``request`` (a :class:`service.sessions.ChunkRequest`) in the next batch."""
        return self._put(("chunk", request))

    def _put(self, item: tuple) -> Future:
        future: Future = Future()
        with self._closing:
            if self._closed:
                raise RuntimeError("the chunk executor is shut down")
            self._queue.put((*item, future))
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop after what was submitted (the chunk in flight and those queued are applied)."""
        with self._closing:
            if not self._closed:
                self._closed = True
                self._queue.put(_STOP)
        if wait:
            self._thread.join()

    # -- the thread ------------------------------------------------------------------
    def _next(self, timeout: float | None = None) -> Any:
        if self._held:
            return self._held.pop(0)
        if timeout is None:
            return self._queue.get()
        if timeout <= 0:
            return self._queue.get_nowait()
        return self._queue.get(timeout=timeout)

    def _loop(self) -> None:
        while True:
            item = self._next()
            if item is _STOP:
                return
            if item[0] == "call":
                _run_call(item)
                continue
            self._apply(self._gather(item))

    def _gather(self, first: tuple) -> list[tuple]:
        """``first`` and the chunks behind it, one per session, up to the first call (a reset keeps
        its place in the order) or the end of the shutdown."""
        batch, sessions, later = [first], {first[1].session_id}, []
        deadline = time.monotonic() + self.window
        while len(batch) < self.max_batch:
            try:
                item = self._next(deadline - time.monotonic())
            except queue.Empty:
                break
            if item is _STOP or item[0] == "call":  # after this batch (and after the chunks held back)
                later.append(item)
                break
            if item[1].session_id in sessions:  # the session's next chunk: in the next batch
                later.append(item)
                continue
            sessions.add(item[1].session_id)
            batch.append(item)
        self._held = later + self._held
        return batch

    def _apply(self, batch: list[tuple]) -> None:
        try:
            metrics.BATCH_SIZE.observe(len(batch))
            answers = self.apply_many([item[1] for item in batch])
            if len(answers) != len(batch):
                raise RuntimeError(f"{len(answers)} answers for {len(batch)} chunks")
        except BaseException as exc:  # noqa: BLE001 - nothing was answered: every chunk gets the error
            answers = [exc] * len(batch)
        for item, answer in zip(batch, answers, strict=True):
            future = item[2]
            if not future.set_running_or_notify_cancel():
                continue
            if isinstance(answer, BaseException):
                future.set_exception(answer)
            else:
                future.set_result(answer)


def _run_call(item: tuple) -> None:
    _, fn, future = item
    if not future.set_running_or_notify_cancel():
        return
    try:
        future.set_result(fn())
    except BaseException as exc:  # noqa: BLE001 - the caller's
        future.set_exception(exc)
