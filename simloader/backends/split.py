"""Simulating on other devices than the one batches are delivered to (`sim_device=`).

A batch of `nbatch` trajectories is split in order across the simulation devices
(`SimConfig.parts`: one configuration per device, each with its share). Each part is an
ordinary backend of the chosen engine on its device, its draws from its own part of the
stream (`sharding.Shard.part`). `produce` starts every part's batch at once, each from a
thread of its own (a closed loop waits on its device at every step, and one thread would
take the devices in turn); `deliver` takes each part's delivered tensors and copies them
into the batch's tensors on `device`, on a copy stream of their own, so that a training loop
queued on `device` neither delays the copies nor is delayed by them; the consumer's stream
then waits for the copies on the GPU, not the host. The copies read from the parts' outputs
while the next batch already simulates (the prefetcher queued it).
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
from collections.abc import Callable
from typing import Any, Optional

import torch

from simloader import handoff, sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig


class SplitBackend(Backend):
    """One batch simulated in parts, one per simulation device, gathered on `device`.

    Args:
      config: with `parts` (one configuration per simulation device).
      shard, stats: as every backend.
      create: makes a part's backend from its configuration, shard and statistics.
    """

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats,
                 create: Callable[[SimConfig, sharding.Shard, Stats], Backend]):
        super().__init__(config, shard, stats)
        n = len(config.parts)
        # each part counts for itself; the batch's counts are gathered in `deliver`
        self.part_stats = [Stats.of(tuple(stats.own)) for _ in range(n)]
        self.counted = [self.part_stats[i].as_dict() for i in range(n)]
        self.parts: list[Backend] = []
        try:
            for i, (part, counts) in enumerate(zip(config.parts, self.part_stats)):
                # one part draws exactly as an unsplit batch does (a single other device)
                part_shard = dataclasses.replace(shard, part=i, parts=n) if n > 1 else shard
                self.parts.append(create(part, part_shard, counts))
        except BaseException:
            self.close()
            raise
        self.threads = concurrent.futures.ThreadPoolExecutor(
            max_workers=n, thread_name_prefix="simloader-part")
        self.device = config.device
        self.copy_stream = (torch.cuda.Stream(self.device) if self.device.type == "cuda"
                            else None)
        self.side: dict[torch.device, Any] = {}  # each source device's copy stream
        # the last batch's part outputs, kept until its copies are done (JAX's buffers are
        # not torch's: nothing but a reference keeps them from being reused)
        self.in_flight: Optional[tuple[Any, list]] = None
        self.first = True

    def produce(self, index: int) -> list:
        # every part's batch queued (or, in a closed loop, run) at once, one thread each;
        # the first batch of the first part alone first: its compilation (MJX) fills the
        # caches the other parts then load instead of compiling the same program at once
        first = [self.parts[0].produce(index)] if self.first else []
        self.first = False
        futures = [self.threads.submit(part.produce, index) for part in self.parts[len(first):]]
        return first + [f.result() for f in futures]

    def deliver(self, produced: list) -> dict[str, Any]:
        delivered = [part.deliver(p) for part, p in zip(self.parts, produced)]
        self._count()
        self._release()
        sizes = [p.nbatch for p in self.config.parts]
        if self.copy_stream is None:
            return _gather(delivered, sizes, self.device)
        sources = {t.device for batch in delivered for t in handoff.tensors(batch)
                   if t.is_cuda}
        # the copies run on streams of their own on both ends (a cross-device copy runs on
        # the source's current stream and orders itself after the target's current stream),
        # each after what the parts' `deliver` queued on its device's current stream (a
        # dtype conversion; on the delivery device itself, after the training's queued work)
        for d in sources:
            if d not in self.side:
                self.side[d] = (self.copy_stream if d == self.device
                                else torch.cuda.Stream(d))
            self.side[d].wait_stream(torch.cuda.current_stream(d))
        with contextlib.ExitStack() as scope:
            # each source device's copy stream current there, then the delivery device's
            for stream in (*self.side.values(), self.copy_stream):
                scope.enter_context(torch.cuda.stream(stream))
            batch = _gather(delivered, sizes, self.device)
            done = torch.cuda.Event()
            done.record(self.copy_stream)
        torch.cuda.current_stream(self.device).wait_event(done)
        handoff.used_here(batch)  # made on the copy stream
        self.in_flight = (done, delivered)
        return batch

    def _count(self) -> None:
        """Adds the batch's counts to the dataset's: one batch, every part's steps and
        diverged trajectories, the slowest part's simulation time, the engines' own."""
        now = [s.as_dict() for s in self.part_stats]
        delta = [{k: a[k] - b[k] for k in a if k != "steps_per_s"}
                 for a, b in zip(now, self.counted)]
        self.counted = now
        self.stats.add(batches=1, steps=sum(d["steps"] for d in delta),
                       diverged=sum(d["diverged"] for d in delta),
                       simulate_s=max(d["simulate_s"] for d in delta),
                       **{k: sum(d[k] for d in delta) for k in self.stats.own})

    def _release(self) -> None:
        """Drops the previous batch's part outputs once its copies are done."""
        if self.in_flight is not None:
            done, _ = self.in_flight
            done.synchronize()
            self.in_flight = None

    def checkpoint(self, produced: list) -> Optional[dict[str, Any]]:
        if not self.config.continue_episodes:
            return None
        return {"parts": [part.checkpoint(p) for part, p in zip(self.parts, produced)]}

    def restore(self, trajectories: dict[str, Any]) -> None:
        saved = trajectories.get("parts") if isinstance(trajectories, dict) else None
        if not isinstance(saved, list) or len(saved) != len(self.parts):
            raise ValueError(f"state_dict: its trajectories were saved by a stream simulated "
                             f"on {len(saved) if isinstance(saved, list) else 'one'} device(s);"
                             f" this one simulates on {len(self.parts)} (sim_device=)")
        for part, state in zip(self.parts, saved):
            part.restore(state)

    def close(self) -> None:
        if getattr(self, "in_flight", None) is not None:
            self._release()
        for part in self.parts:
            part.close()
        if hasattr(self, "threads"):
            self.threads.shutdown(wait=True)


def _gather(delivered: list[dict], sizes: list[int], device: torch.device) -> dict:
    """The parts' batches as one on `device`: each key's rows in part order; a value without
    a row per trajectory (the policy's version) from the first part."""
    out = {}
    for key, first in delivered[0].items():
        if isinstance(first, dict):
            out[key] = _gather([d[key] for d in delivered], sizes, device)
            continue
        if first.dim() == 0 or first.shape[0] != sizes[0]:
            out[key] = first.to(device, non_blocking=True)
            continue
        whole = torch.empty((sum(sizes), *first.shape[1:]), dtype=first.dtype, device=device)
        start = 0
        for part, n in zip(delivered, sizes):
            whole[start:start + n].copy_(part[key], non_blocking=True)
            start += n
        out[key] = whole
    return out

