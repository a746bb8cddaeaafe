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
from typing import Any, Optional

_END = object()
_POLL_S = 0.1
_LIVE: "weakref.WeakSet[Prefetcher]" = weakref.WeakSet()
_registered = False


def _stop_all() -> None:
    """At interpreter exit, stops the producers still running (an iterator left open) and
    runs their `at_exit` callbacks (the backend's `close`, which frees native thread pools). A
    daemon thread that comes back from native code (JAX's dispatch, MuJoCo's rollout) after the
    interpreter began to finalize is killed inside it, and a native thread pool destroyed
    during teardown (modules half gone) may be destroyed with its threads still joinable;
    either aborts the process ("terminate called without an active exception", exit -6).
    Registered when the first producer starts, so after JAX's own exit handlers and hence run
    before them. Every producer is stopped before any callback runs, and one that fails does
    not keep the others from running."""
    live = list(_LIVE)
    for prefetcher in live:
        try:
            prefetcher.close()
        except BaseException:  # noqa: BLE001 - at exit: stop the others regardless
            pass
    for prefetcher in live:
        prefetcher._run_at_exit()


class _Failure:
    def __init__(self, error: BaseException):
        self.error = error


class Prefetcher:
    """Iterates `produce(i) for i in indices`, computed `depth` items ahead in a thread."""

    def __init__(self, produce: Callable[[int], Any], indices: Iterable[int], depth: int,
                 at_exit: Optional[Callable[[], None]] = None):
        """`at_exit`: called (once) at interpreter exit if this prefetcher is still open then,
        after its producer stopped: what `produce` needs closed before the interpreter tears
        down (the backend's `close`)."""
        self._produce: Optional[Callable[[int], Any]] = produce
        self._indices = indices
        self._at_exit = at_exit
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
        produce, indices = self._produce, self._indices
        try:
            for i in indices:
                if self._stop.is_set() or not self._put(produce(i)):
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
                    if self._stop.is_set():  # closed: the stream ends here
                        return
                    raise RuntimeError("simloader: the prefetch thread ended unexpectedly")
                continue
            if item is _END:
                return
            if isinstance(item, _Failure):
                raise item.error
            yield item

    def close(self) -> None:
        """Stops the producer after its current item and waits for it. Once closed, a second
        close returns at once without touching any module: the generator that owns this
        prefetcher may be finalized after interpreter teardown emptied them (`_stop_all`
        closed it before)."""
        if self._produce is None:
            return
        self._stop.set()
        if threading.current_thread() is self._thread:
            # the consumer's generator was dropped and finalized by a garbage collection that
            # ran on the producer thread itself: it cannot wait for itself; it stops after this
            # item, as asked (seen once in the suite: "cannot join current thread")
            return
        while self._thread.is_alive():
            try:  # unblock a producer waiting on a full queue
                self._queue.get_nowait()
            except queue.Empty:
                pass
            self._thread.join(timeout=_POLL_S)
        # the producer is gone: drop what it referenced (the backend, through `produce`), so
        # that a closed prefetcher kept alive by someone does not keep a thread pool alive
        self._produce = self._indices = None
        _LIVE.discard(self)

    def _run_at_exit(self) -> None:
        callback, self._at_exit = self._at_exit, None
        if callback is not None:
            try:
                callback()
            except BaseException:  # noqa: BLE001 - at exit: nothing left to report it to
                pass
