"""The small interface both backends implement, and the statistics they keep.

A backend is created in the process that iterates (a DataLoader worker, or the main process)
and is used by two threads: `produce` runs in the prefetch thread (simulation, which releases
the GIL or dispatches asynchronously), `deliver` in the consumer thread (the torch hand-off and
the checks that can overlap with the next batch's simulation). Both produce the same schema:
`state`, `sensordata`, `control`, `initial_state`, `diverged`.
"""

from __future__ import annotations

import abc
import dataclasses
import threading
from typing import Any, Optional

import numpy as np
import torch

from simloader import sharding
from simloader.config import SimConfig


@dataclasses.dataclass
class Stats:
    """Counters of one iterator (one DataLoader worker, or the main process).

    Attributes:
      batches: batches delivered.
      steps: simulated steps delivered (trajectories x steps).
      diverged: trajectories flagged as diverged.
      simulate_s: seconds spent simulating (CPU backend: in MuJoCo; MJX: until results ready).
      compile_s: seconds spent compiling (MJX backend).
      compiles: compilations (MJX backend): one per configuration, never per batch.
      overflow: trajectories that lost contacts or constraint rows to MuJoCo Warp's buffer
        sizes (impl="warp"; flagged in the batch's `overflow`).
      solver_limit: trajectories whose constraint solver stopped at its iteration limit in a
        batch (impl="warp"; MuJoCo C stops there too, silently).
    """

    batches: int = 0
    steps: int = 0
    diverged: int = 0
    simulate_s: float = 0.0
    compile_s: float = 0.0
    compiles: int = 0
    overflow: int = 0
    solver_limit: int = 0
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock, repr=False)

    def add(self, **values: float) -> None:
        with self.lock:
            for k, v in values.items():
                setattr(self, k, getattr(self, k) + v)

    def __getstate__(self) -> dict:
        # a worker process gets its own counters (and lock)
        return {k: v for k, v in self.__dict__.items() if k != "lock"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, lock=threading.Lock())

    def as_dict(self) -> dict[str, float]:
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "lock"}
        out["steps_per_s"] = self.steps / self.simulate_s if self.simulate_s else 0.0
        return out


class Backend(abc.ABC):
    """Simulates batches for one shard of the stream."""

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats):
        self.config = config
        self.shard = shard
        self.stats = stats

    def seed(self, index: int, purpose: int) -> np.random.SeedSequence:
        return sharding.batch_seed(self.config.seed, self.shard, index, purpose)

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
