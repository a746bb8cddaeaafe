"""Work of torch operations and MuJoCo Warp launches on one CUDA stream, captured as one CUDA
graph: the Warp engine's step (`engine.WarpSimulation`) and the render of stored states
(`stored.StoredRenderer`). A replay costs one launch where the work is dozens of small
kernels, each with its Python launch overhead.

The work runs once eagerly first (it loads MuJoCo Warp's kernels and torch's, which a capture
cannot), then is captured by torch on `stream`, in thread-local mode, with garbage collection
paused (a collection inside the capture could free device memory), while MuJoCo Warp's
launches are registered as an external capture of the same stream. Everything the work reads
and writes must be device memory that outlives the graph, and whatever the work allocated
during the capture is kept by the Warp graph object (`Captured.warp_graph`), which lives as
long as the graph: dropped, that memory is freed and reused while the graph still reads and
writes it (illegal accesses, seen on an H200). Callers hold `runtime.WARP_LOCK`.
"""

from __future__ import annotations

import contextlib
import gc
from collections.abc import Callable
from typing import Any

import torch


class Captured:
    """`work()` captured on `stream` (a torch CUDA stream of `device`; `warp_stream`: Warp's
    handle of it), after one eager run there. The stream waits for the device's current
    stream first, and the current stream for the capture at the end."""

    def __init__(self, wp: Any, work: Callable[[], None], device: torch.device,
                 stream: torch.cuda.Stream, warp_stream: Any):
        self.stream = stream
        current = torch.cuda.current_stream(device)
        stream.wait_stream(current)
        self.graph = torch.cuda.CUDAGraph()
        self.warp_graph = None
        with torch.cuda.stream(stream), wp.ScopedStream(warp_stream, sync_enter=False):
            work()
        with _paused_collection(), \
                torch.cuda.graph(self.graph, stream=stream, capture_error_mode="thread_local"), \
                wp.ScopedStream(warp_stream, sync_enter=False):
            wp.capture_begin(stream=warp_stream, external=True, force_module_load=False)
            try:
                work()
            finally:
                self.warp_graph = wp.capture_end(stream=warp_stream)
        current.wait_stream(stream)

    def replay(self) -> None:
        """The work again, on the stream current now."""
        self.graph.replay()

    def release(self) -> None:
        """Waits for the replays queued on the capture's stream, then frees the graph."""
        self.stream.synchronize()
        self.graph.reset()
        self.graph = self.warp_graph = None


@contextlib.contextmanager
def _paused_collection():
    collecting = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if collecting:
            gc.enable()
