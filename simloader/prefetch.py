"""A producer thread that simulates ahead of the consumer, with a bounded queue.

The thread calls `produce(i)` for each index and puts the result in a queue of `depth` slots, so
at most `depth` batches wait while the consumer works on another. An exception in the producer
is re-raised in the consumer with its type and traceback; `close()` stops and joins the thread
(the consumer side is a generator, so breaking out of a loop closes it).
"""

from __future__ import annotations

import atexit
import queue
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator
from typing import Any

_END = object()
_POLL_S = 0.1
_LIVE: "weakref.WeakSet[Prefetcher]" = weakref.WeakSet()
_registered = False


def _stop_all() -> None:
    """At interpreter exit, stops the producers still running (an iterator left open). A
    daemon thread that comes back from native code (JAX's dispatch, MuJoCo's rollout) after the
    interpreter began to finalize is killed inside it, which aborts the process ("terminate
    called ... FATAL: exception not rethrown"). Registered when the first producer starts, so
    after JAX's own exit handlers and hence run before them."""
    for prefetcher in list(_LIVE):
        prefetcher.close()


class _Failure:
    def __init__(self, error: BaseException):
        self.error = error


class Prefetcher:
    """Iterates `produce(i) for i in indices`, computed `depth` items ahead in a thread."""

    def __init__(self, produce: Callable[[int], Any], indices: Iterable[int], depth: int):
        self._produce = produce
        self._indices = indices
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="simloader-prefetch", daemon=True)
        global _registered
        if not _registered:
            atexit.register(_stop_all)
            _registered = True
        _LIVE.add(self)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def _run(self) -> None:
        try:
            for i in self._indices:
                if self._stop.is_set() or not self._put(self._produce(i)):
                    return
            self._put(_END)
        except BaseException as e:  # re-raised in the consumer
            self._put(_Failure(e))

    def __iter__(self) -> Iterator[Any]:
        while True:
            try:
                item = self._queue.get(timeout=_POLL_S)
            except queue.Empty:
                if not self._thread.is_alive() and self._queue.empty():
                    raise RuntimeError("simloader: the prefetch thread ended unexpectedly")
                continue
            if item is _END:
                return
            if isinstance(item, _Failure):
                raise item.error
            yield item

    def close(self) -> None:
        """Stops the producer after its current item and waits for it."""
        self._stop.set()
        while self._thread.is_alive():
            try:  # unblock a producer waiting on a full queue
                self._queue.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(timeout=_POLL_S)
