"""The small interface both backends implement, and the statistics they keep.

A backend is created in the process that iterates (a DataLoader worker, or the main process)
and is used by two threads: `produce` runs in the prefetch thread (simulation, which releases
the GIL or dispatches asynchronously), `deliver` in the consumer thread (the torch hand-off and
the checks that can overlap with the next batch's simulation). Every engine delivers the same
keys for a configuration: those of `record=`, `control`, `initial_state` and `diverged`,
`params` when randomized, `policy/...` in the closed loop, and its own flags (`overflow` on
MuJoCo Warp).
"""

from __future__ import annotations

import abc
import contextlib
import dataclasses
import multiprocessing
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, Optional

import numpy as np
import torch

from simloader import randomize as dr
from simloader import seeds, sharding, terminate
from simloader.config import SimConfig


@dataclasses.dataclass
class Stats:
    """Counters of one iterator (one DataLoader worker, or the main process): those every
    engine keeps, and the engine's own (`Engine.counters`, documented in its `entry.py`).

    Attributes:
      batches: batches delivered.
      steps: simulated steps delivered (trajectories x steps).
      diverged: trajectories flagged as diverged.
      simulate_s: seconds spent simulating (CPU engine: in MuJoCo; GPU engines: until results
        ready).
      own: the engine's own counters by name, each from 0.
    """

    batches: int = 0
    steps: int = 0
    diverged: int = 0
    simulate_s: float = 0.0
    own: dict[str, float] = dataclasses.field(default_factory=dict)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock, repr=False)

    @classmethod
    def of(cls, counters: tuple[str, ...]) -> "Stats":
        """Counters for an engine whose own are `counters`."""
        return cls(own=dict.fromkeys(counters, 0))

    def add(self, **values: float) -> None:
        with self.lock:
            for k, v in values.items():
                if k in self.own:
                    self.own[k] += v
                else:
                    setattr(self, k, getattr(self, k) + v)  # AttributeError: not a counter

    def __getstate__(self) -> dict:
        # a worker process gets its own counters (and lock)
        return {k: (dict(v) if k == "own" else v) for k, v in self.__dict__.items()
                if k != "lock"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, lock=threading.Lock())

    def as_dict(self) -> dict[str, float]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name not in ("lock", "own")}
        out.update(self.own)
        out["steps_per_s"] = self.steps / self.simulate_s if self.simulate_s else 0.0
        return out


class Backend(abc.ABC):
    """Simulates batches for one shard of the stream."""

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats):
        self.config = config
        self.shard = shard
        self.stats = stats

    def seed(self, index: int, purpose: int) -> np.random.SeedSequence:
        return seeds.batch_seed(self.config.seed, self.shard, index, purpose)

    def draw_models(self, index: int) -> dict[str, np.ndarray]:
        """Batch `index`'s host draws of what each trajectory runs on: its variant
        ("variant", (nbatch,)) and its randomized values ({key: (nbatch, ...)}), from the
        batch's randomization seed; the engines that draw these on the host draw them here."""
        c = self.config
        seed = self.seed(index, seeds.RANDOMIZE)
        drawn = {}
        if c.variants is not None:
            drawn["variant"] = dr.draw_variants(seed, len(c.variants), c.nbatch)
        if c.randomization is not None:
            drawn.update(c.randomization.sample(seed, c.nbatch))
        return drawn

    def fresh_draw(self, index: int, draw: int) -> np.ndarray:
        """(nbatch, nstate): batch `index`'s `draw`-th set of fresh initial states from the
        initial-state generator, one per trajectory (`terminate=`'s autoreset: a
        trajectory's e-th reset of the batch takes its row of draw `e % FRESH_DRAWS`), the
        same on every engine."""
        c = self.config
        return c.initial.sample(seeds.reset_seed(c.seed, self.shard, index, draw), c.nbatch)

    def fresh_draws(self, index: int) -> Optional[np.ndarray]:
        """(nbatch, FRESH_DRAWS, nstate): all of batch `index`'s `fresh_draw`s, for the
        engines that hand them to the device at once; None without `terminate=` or without
        an initial-state generator (a reset restarts from the trajectory's own state)."""
        c = self.config
        if c.terminate is None or c.initial.generator is None:
            return None
        return np.stack([self.fresh_draw(index, d) for d in range(terminate.FRESH_DRAWS)],
                        axis=1)

    @abc.abstractmethod
    def produce(self, index: int) -> Any:
        """Simulates global batch `index` (called in order, from the prefetch thread)."""

    @abc.abstractmethod
    def deliver(self, produced: Any) -> dict[str, torch.Tensor]:
        """Turns a produced batch into the delivered dict of tensors (consumer thread)."""

    def checkpoint(self, produced: Any) -> Optional[dict[str, Any]]:
        """JSON-serializable trajectory state after `produced` (continue_episodes), or None."""
        if self.config.continue_episodes:
            raise NotImplementedError(
                f"{type(self).__name__} cannot checkpoint continuing episodes yet")
        return None

    def restore(self, trajectories: dict[str, Any]) -> None:
        """Continues from trajectory state saved by `checkpoint` (before the first produce)."""
        raise NotImplementedError(f"{type(self).__name__} cannot restore continuing episodes")

    def close(self) -> None:
        """Releases threads and device buffers; the backend is not used afterwards."""


def refuse_forked_worker(what: str, why: str) -> None:
    """Raises RuntimeError in a forked DataLoader worker, for an engine that cannot run after
    fork (`what` names it, `why` says why)."""
    if torch.utils.data.get_worker_info() is None:
        return
    # a DataLoader started with a context uses its Process class, which names its start
    # method; a plain Process uses the global one, which a forked child inherits
    method = (getattr(multiprocessing.current_process(), "_start_method", None)
              or multiprocessing.get_start_method())
    if method == "fork":
        raise RuntimeError(
            f"{what} cannot run in a forked DataLoader worker: {why}. Use num_workers=0 (a GPU "
            f"batch already runs in parallel on the device) or DataLoader(..., "
            f"multiprocessing_context='spawn').")


@contextlib.contextmanager
def progress_line(what: str, *, after: float = 0.0, hint: str = "",
                  estimate_s: Optional[float] = None) -> Iterator[None]:
    """Says on stderr that `what` runs, once it has run `after` seconds (at once by default),
    and then how long it took: one opaque call that can take a minute (a cold compilation)
    must not look like a hang. On a terminal the line ticks every second. `hint`: said with
    it; `estimate_s`: how long the last one took, shown when known."""
    last = f" (the last one took {estimate_s:.0f} s)" if estimate_s is not None else ""
    tty = sys.stderr.isatty()
    start = time.perf_counter()
    stop, said = threading.Event(), threading.Event()

    def write(text: str) -> None:
        # on a terminal one line, rewritten in place; in a log file a line per message.
        # Written by hand, not with tqdm: its write lock deadlocked against tqdm's monitor
        # thread when this ran in a prefetch thread (a pytest-xdist worker, 2026-11-25)
        sys.stderr.write(f"\rsimloader: {what}{text}\x1b[K" if tty else
                         f"simloader: {what}{text}\n")
        sys.stderr.flush()

    def announce() -> None:
        said.set()
        write(f"{last}...{' ' + hint if hint else ''}")

    def watch() -> None:
        if after > 0:
            if stop.wait(after):
                return
            announce()
        while tty and not stop.wait(1.0):
            write(f"{last}: {time.perf_counter() - start:.0f} s")

    if after <= 0:
        announce()  # now, not from the thread: said even if `what` ends at once
    watcher = threading.Thread(target=watch, daemon=True, name="simloader-progress")
    watcher.start()
    try:
        yield
    finally:
        stop.set()
        watcher.join()
        if said.is_set():
            write(f": done in {time.perf_counter() - start:.0f} s")
            if tty:
                sys.stderr.write("\n")


def slow_notice(what: str, after: float = 10.0, hint: str = "") -> Any:
    """`progress_line` said only when `what` takes longer than `after` seconds."""
    return progress_line(what, after=after, hint=hint)
