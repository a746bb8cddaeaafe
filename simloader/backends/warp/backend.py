"""The Warp engine (`backend="warp"`): MuJoCo Warp driven from torch, no JAX.

Each batch is drawn on the host exactly as the CPU backend draws it (initial states,
randomized parameters, variants and controls from the same seeds, with NumPy), moved to the
device once, and applied there: per-trajectory model arrays, the reset of the trajectories
that start afresh, the clamp bounds. Then `nstep` replays of the engine's step graph (open
loop), or `nstep` policy calls each followed by one replay (closed loop). Decisions that
depend on the previous batch (which trajectories restart, the models they keep) stay on the
device, so the host never waits for the GPU while it queues a batch. `deliver` waits for the
batch, counts what the stats count, and hands over the outputs: tensors of their own, copied
on the device from the engine's fixed buffers at the end of the batch (the graph writes at
fixed addresses; the copies cost a few hundred microseconds per batch).
"""

from __future__ import annotations

import time
import warnings
import weakref
from typing import Any, Optional

import numpy as np
import torch

from simloader import handoff, policy, resume, seeds, sharding
from simloader.backends.base import Backend, Stats, refuse_forked_worker, slow_notice
from simloader.backends.warp import options as warp_options
from simloader.backends.warp import runtime
from simloader.backends.warp.engine import WarpSimulation
from simloader.config import SimConfig
from simloader.trajectories import Trajectories

# engines by configuration and device: every iterator (epoch) of a dataset replays the graph
# its first one captured; an engine goes away with its dataset's configuration
_ENGINES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_FIRST_USE = ("MuJoCo Warp compiles its kernels for this model on first use on a machine "
              "(about a minute for a humanoid on an H200, into ~/.cache/warp; later processes "
              "load them in seconds). `simloader warmup` does it ahead of time.")


class _Produced:
    """A batch queued on the device: its outputs (maybe not computed yet) and when."""

    def __init__(self, outputs: dict, params: dict, extras: dict, rows_after: Any,
                 ready: Any, dispatched: float, episodes: Optional[tuple] = None):
        self.outputs, self.params, self.extras = outputs, params, extras
        self.rows_after, self.ready, self.dispatched = rows_after, ready, dispatched
        # terminate= with continue_episodes: (pending, episode steps) after this batch
        self.episodes = episodes


class WarpBackend(Backend):
    """`backend="warp"`.

    Raises:
      RuntimeError: in a forked DataLoader worker on a GPU (CUDA cannot start after fork).
    """

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats,
                 options: warp_options.WarpOptions):
        super().__init__(config, shard, stats)
        self.options = options
        self.device = runtime.sim_device(config.device)
        if self.device.type == "cuda":
            refuse_forked_worker("backend='warp'", "CUDA cannot start in a forked child of a "
                                 "process that started it")
        engines = _ENGINES.setdefault(config, {})
        self.engine: WarpSimulation = engines.get(self.device)
        if self.engine is None:
            start = time.perf_counter()
            with slow_notice("building MuJoCo Warp's step for this model", hint=_FIRST_USE):
                self.engine = engines[self.device] = WarpSimulation(
                    config, options, self.device,
                    on_capture=lambda: stats.add(graph_captures=1))
            stats.add(compile_s=time.perf_counter() - start)
        self.tables = self.engine.tables
        # which trajectories start afresh, the variant and values each runs with (on the device)
        self.trajectories = Trajectories(config, self.device)
        self.restored: Optional[torch.Tensor] = None  # resumed rows, applied at the next batch
        # terminate= with continue_episodes: (pending, episode steps) this iterator's episodes
        # left, and those to load at the next batch (resumed, or taken back)
        self.episodes_after: Optional[tuple] = None
        self.restored_episodes: Optional[tuple] = None
        self.rows: Optional[torch.Tensor] = None  # continuing: the rows after the last batch
        self.token = object()  # names this iterator as the engine's owner (holding nothing)
        self.snapshot = (policy.Snapshot(config.policy, self.device)
                         if config.policy is not None else None)
        self.last_ready = 0.0
        self.warned_overflow = False
        self.last: Optional[_Produced] = None

    # -- host draws ------------------------------------------------------------------------

    def upload(self, array: np.ndarray) -> torch.Tensor:
        """A host array on the simulation device, real values in float32, integers (variant
        indices) as they are (through pinned memory, queued on the current stream: inside
        `queued`, the engine's)."""
        array = np.asarray(array)
        host = torch.from_numpy(np.ascontiguousarray(
            array, dtype=np.float32 if array.dtype.kind == "f" else None))
        if self.device.type == "cuda":
            host = host.pin_memory()
        return host.to(self.device, non_blocking=True)

    # -- one batch -------------------------------------------------------------------------

    def produce(self, index: int) -> _Produced:
        c, e, tables = self.config, self.engine, self.tables
        # the host's draws first (no lock held), put on the device inside `queued`: uploaded
        # on the engine's stream, they are ordered before the reset that reads them (on the
        # producer's own stream, the legacy default one that the consumer trains on, the
        # reset could read them before they arrived)
        x0 = c.initial.sample(self.seed(index, seeds.INITIAL), c.nbatch)
        drawn = self.draw_models(index)
        fresh = self.fresh_draws(index)  # a generator's, for the autoreset
        # the weights this batch runs with, one version of them (a copy taken now)
        weights = self.snapshot.take() if self.snapshot is not None else None
        dispatched = time.perf_counter()
        with e.queued():
            starts_afresh = self.trajectories.fresh.clone()
            x0 = self._start_trajectories({k: self.upload(v) for k, v in drawn.items()},
                                          self.upload(x0))
            if e.episodes is not None:
                if self.restored_episodes is not None:
                    for buffer, value in zip((e.episodes.pending, e.episodes.steps),
                                             self.restored_episodes):
                        buffer.copy_(torch.as_tensor(value, device=self.device))
                    self.restored_episodes = None
                e.episodes.start(x0[:, None] if fresh is None else self.upload(fresh),
                                 self.trajectories.per_trajectory(tables.control_defaults),
                                 starts_afresh)
            initial_state = e.physics()
            e.set_bounds(self.trajectories.per_trajectory(tables.low),
                         self.trajectories.per_trajectory(tables.high))
            e.loop.prepare(self.seed(index, seeds.CONTROL),
                           self.trajectories.per_trajectory(tables.control_defaults))
            e.start()
            extras = e.loop.run(weights)
            e.finish()
            outputs = {k: v.clone() for k, v in e.frames.items()}
            outputs.update(control=e.applied(), diverged=e.diverged.clone(),
                           initial_state=initial_state,
                           overflow=e.views["overflow"][:, 0].clone())
            episodes = None
            if e.episodes is not None:
                outputs.update(e.episodes.finish(outputs["control"]))
                if c.continue_episodes:  # what the next batch (or a checkpoint) takes on
                    episodes = (e.episodes.pending.clone(), e.episodes.steps.clone())
                    self.episodes_after = episodes
            params = {k: v.clone() for k, v in self.trajectories.params.items()}
            rows_after = e.integration() if c.continue_episodes else None
            self.rows = rows_after
            # which rows start afresh next batch: on the engine's stream, ordered after the
            # steps that wrote the flags (a copy: the consumer may edit its own)
            self.trajectories.finished(outputs["diverged"].clone())
            ready = torch.cuda.Event() if e.gpu else None
            if ready is not None:
                ready.record()
        produced = _Produced(outputs, params, extras, rows_after, ready, dispatched, episodes)
        self.last = produced
        return produced

    def _start_trajectories(self, drawn: dict[str, torch.Tensor],
                            x0: torch.Tensor) -> torch.Tensor:
        """Trajectories that start afresh (all, unless continuing) take their newly drawn
        model (variant) and parameters and restart from their initial state; the others keep
        theirs. Returns each trajectory's initial state (its source's row: the fresh state of
        an autoreset where no generator draws them)."""
        c, e, tables, t = self.config, self.engine, self.tables, self.trajectories
        fresh = t.fresh
        if e.claim(self.token) and self.restored is None and c.continue_episodes:
            # another iterator of this dataset ran on the engine's data since: take back
            # this one's trajectories (the rows it left, warmstart included)
            self.restored = self.rows
            self.restored_episodes = self.episodes_after
        if self.restored is not None:  # resumed or taken back: the rows, before any restart
            e.reset(self.restored, torch.ones_like(fresh))
            self.restored = None
        t.take(drawn)
        e.set_model(t.model_index, t.params)
        rows = t.per_trajectory(tables.reset_rows).clone()
        if tables.variant_states is not None:
            x0 = t.per_trajectory(tables.variant_states)
        rows[:, tables.physics_cols] = x0
        e.reset(rows, fresh)
        return x0

    def deliver(self, produced: _Produced) -> dict[str, torch.Tensor]:
        c = self.config
        if produced.ready is not None:
            produced.ready.synchronize()
        ready = time.perf_counter()
        out = produced.outputs
        self.stats.add(simulate_s=ready - max(produced.dispatched, self.last_ready),
                       batches=1, steps=c.nbatch * c.nstep,
                       diverged=int(out["diverged"].sum()))
        self.last_ready = ready
        rendered = {o.key for o in c.observations if o.rendered}
        batch = {k: handoff.to_target(v, c.device, c.dtype if v.is_floating_point()
                                      and k not in rendered else None)
                 for k, v in out.items() if k != "overflow"}
        batch["overflow"] = handoff.to_target(self._overflow(out["overflow"]), c.device, None)
        batch.update({k: handoff.to_target(v, c.device, None)
                      for k, v in produced.extras.items()})
        if produced.params:
            batch["params"] = {k: handoff.to_target(v, c.device, None if k == "variant"
                                                    else c.dtype)
                               for k, v in produced.params.items()}
        handoff.used_here(batch)  # made on the engine's stream
        return batch

    def _overflow(self, bits: torch.Tensor) -> torch.Tensor:
        """MuJoCo Warp's overflow bits of a batch: counted in `stats` (solver iteration limits
        apart), warned about once with what to raise; the per-trajectory flag delivered."""
        host = bits.cpu().numpy()
        dropped = (host & ~warp_options.SOLVER_LIMIT) != 0
        self.stats.add(overflow=int(dropped.sum()),
                       solver_limit=int(((host & warp_options.SOLVER_LIMIT) != 0).sum()))
        if dropped.any() and not self.warned_overflow:
            self.warned_overflow = True
            o = self.options
            bits = int(np.bitwise_or.reduce(host[dropped]))
            warnings.warn(
                f"simloader: {int(dropped.sum())} of {len(host)} trajectories lost contacts or "
                f"constraints to MuJoCo Warp's buffer sizes (flagged in batch['overflow']): "
                f"{warp_options.overflow_message(bits, o.naconmax, o.njmax)} (MuJoCo Warp's "
                f"overflow bits {bits:#x})",
                RuntimeWarning, stacklevel=2)
        return torch.from_numpy(dropped)

    def checkpoint(self, produced: _Produced) -> Optional[dict[str, Any]]:
        if not self.config.continue_episodes:
            return None
        encoded = self.trajectories.checkpoint(produced.rows_after,
                                               produced.outputs["diverged"], produced.params)
        if produced.episodes is not None:
            encoded["episodes"] = resume.encode_episodes(
                *(v.cpu().numpy() for v in produced.episodes))
        return encoded

    def restore(self, trajectories: dict[str, Any]) -> None:
        # the rows are loaded at the next batch, inside the engine's stream
        self.restored = self.trajectories.restore(trajectories)
        if self.engine.episodes is not None:
            pending, steps = resume.decode_episodes(trajectories, self.config.nbatch)
            self.restored_episodes = (pending, steps)

    def close(self) -> None:
        # batches queued but never delivered would keep the GPU busy after the iterator is
        # gone; the stream runs them in order, so waiting for the last waits for all
        if self.last is not None and self.last.ready is not None:
            self.last.ready.synchronize()
        self.last = None

