"""Timing simloader and the raw simulators alike: alternating repetitions, medians, the
delivered stream timed with its tensors in hand (`shared/design/performance.md`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from typing import Any, Optional

import mujoco
import torch

from simloader.bench.raw import Workload


def cpu_count() -> int:
    """CPU cores this process may run on (what simloader's CPU engine uses)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def device_name(device: torch.device) -> str:
    """What a torch device is, for the "runs on" column ("NVIDIA H200", "CPU")."""
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"


# -- timing -----------------------------------------------------------------------------------

def sync() -> None:
    """Waits for the GPU work queued on torch's current stream.

    Not a device-wide `torch.cuda.synchronize()`: simloader orders each delivered batch before
    the consumer's stream, so that stream is all a timing of delivered batches must wait for;
    a device-wide synchronize would also wait for the batches the producer thread simulates
    ahead, and time them twice.
    """
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.current_stream().synchronize()


def drain() -> None:
    """Waits until the work already dispatched to the devices has run.

    simloader's MJX producer dispatches batches ahead; those an iterator was closed on still
    run on the device and would slow whatever is timed next. Devices run their work in order,
    so a tiny computation on each, waited for, waits for them.
    """
    sync()
    jax = sys.modules.get("jax")
    if jax is not None:
        for device in jax.local_devices():
            jax.block_until_ready(jax.device_put(0, device) + 1)


def progress(iterable: Iterable, desc: str = "", total: Optional[int] = None) -> Iterable:
    """A tqdm progress bar on stderr (sparse when stderr is a log file)."""
    from tqdm import tqdm
    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr,
                mininterval=1.0 if sys.stderr.isatty() else 30.0)


def interleave(measures: dict[str, Callable[[], float]], repeats: int,
               desc: str = "",
               each: Optional[dict[str, list[float]]] = None) -> dict[str, float]:
    """The median of each measure's result, the measures run alternately `repeats` times.

    Each measure times its own steady part (warm-up excluded) and returns seconds per
    simulated step. The order is reversed every repetition, so that drift in the machine
    (clocks, caches, other load) touches every measure alike. `each`: filled with every
    repetition's result per measure, in the order run (how much the machine moved).
    """
    times: dict[str, list[float]] = {} if each is None else each
    times.update({name: [] for name in measures})
    order = list(measures)
    for rep in progress(range(repeats), desc=desc):
        for name in order if rep % 2 == 0 else reversed(order):
            times[name].append(measures[name]())
    return {name: statistics.median(times[name]) for name in measures}


def batches_for(batch_s: float, min_batches: int, min_seconds: float) -> int:
    """Timed batches per repetition: `min_batches`, or more to last `min_seconds`."""
    return max(min_batches, math.ceil(min_seconds / max(batch_s, 1e-9)))


@dataclasses.dataclass
class Stream:
    """One pass over a dataset: `first_s` to the first batch, `steady_s` for the rest."""

    first_s: float
    steady_s: float
    last: Optional[dict[str, torch.Tensor]] = None


def time_stream(ds: Iterable[dict[str, torch.Tensor]], nbatches: int,
                keep_last: bool = False,
                on_batch: Optional[Callable[[dict], None]] = None) -> Stream:
    """Delivered throughput of a dataset: `nbatches` batches after the first, tensors in hand.

    A fresh iterator per call: simloader's producer thread starts with it and stops at
    `close`, and the device is drained, so nothing simulates while another measure runs. The
    first batch, which pays for threads, compilation and the empty prefetch queue, is timed
    apart; the steady part runs from holding the first batch to holding the last, blocked on
    the device after each. `on_batch` sees each steady batch (a mixture's draws, say).
    """
    it = iter(ds)
    try:
        start = time.perf_counter()
        batch = next(it)
        sync()
        first = time.perf_counter()
        for _ in range(nbatches):
            del batch  # release a (possibly multi-GB) batch before the next arrives
            batch = next(it)
            sync()
            if on_batch is not None:
                on_batch(batch)
        return Stream(first - start, time.perf_counter() - first, batch if keep_last else None)
    finally:
        it.close()
        drain()


# -- simloader, measured the same way ---------------------------------------------------------

class SimloaderMeasure:
    """A simloader dataset, warmed up by one pass (which compiles on MJX), then measured.

    Attributes:
      ds: the dataset; first_s: seconds to its first batch (compilation included);
      compile_s: of which compiling; shapes, device: of the delivered batch.
    """

    def __init__(self, model: mujoco.MjModel, w: Workload, backend: str, seed: int,
                 **options: Any):
        import simloader  # imported late: benchmarks/ put their checkout first on sys.path
        self.w = w
        options = {"control": simloader.controls.Uniform(), **options}
        self.ds = simloader.SimDataset(model, backend=backend, nbatch=w.nbatch, nstep=w.nstep,
                                       seed=seed, **options)
        first = time_stream(self.ds, 0, keep_last=True)
        self.first_s = first.first_s
        self.compile_s = self.ds.stats.get("compile_s", 0.0)
        self.shapes = {k: tuple(v.shape) for k, v in first.last.items() if k != "params"}
        self.device = first.last["control"].device
        del first

    def measure(self, nbatches: int) -> float:
        """Seconds per step of `nbatches` delivered batches after a fresh iterator's first."""
        return time_stream(self.ds, nbatches).steady_s / (nbatches * self.w.steps)


def read_frames(loader: Iterable[dict], frames: int, per_item: int,
                key: Optional[str] = None) -> float:
    """Seconds per frame a loader of rendered images delivers until `frames` frames, after its
    first batch (workers and renderers started), passing over it as often as needed.

    Args:
      per_item: frames per item of a batch (a trajectory's frames, or 2 for a transition).
      key: the images' key (None: the first key starting with "camera/").
    """
    done, start = 0, None
    while done < frames:
        for batch in loader:
            images = batch[key] if key is not None else next(
                v for k, v in batch.items() if k.startswith("camera/"))
            sync()
            if start is None:
                start = time.perf_counter()
                continue
            done += len(images) * per_item
            if done >= frames:
                break
    return (time.perf_counter() - start) / done
