"""CPU backend: MuJoCo's native batched simulation (`mujoco.batch.Batch`) on a thread pool.

Each trajectory is an `mjSTATE_INTEGRATION` row of the batch (solver warmstart included), so a
batch that continues the previous one starts exactly where it ended. `Batch.rollout` records what
`record=` names (the `mjSTATE_FULLPHYSICS` state and the sensors by default; any MjData field)
straight into NumPy views of new torch tensors: the delivered tensors are the buffers MuJoCo
wrote (or views of them), and every batch equals `mujoco.rollout` on the same inputs bit for
bit, at any thread count.

Rows are initialized as `mujoco.rollout` initializes its MjData: user inputs outside
`control_spec` as `mj_resetData` leaves them (zero controls and forces, mocap bodies at their
model poses, `eq_active0`), the FULLPHYSICS part from the initial state, zero warmstart.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Optional, Union

import numpy as np
import torch
from mujoco import batch as mj_batch

from simloader import controls, handoff, layout, mujoco_warnings, resume, rules, seeds, terminate
from simloader import threads
from simloader.backends.cpu import drivers
from simloader.backends.cpu import episodes as cpu_episodes
from simloader.backends.cpu import recorded as recorded_from
from simloader import render as cpu_render
from simloader.backends.base import Backend
from simloader.trajectories import Trajectories


@dataclasses.dataclass
class _Produced:
    recorded: dict[Union[str, int], torch.Tensor]  # by `mujoco.batch` record item (source)
    control: torch.Tensor
    initial_state: torch.Tensor
    params: dict[str, torch.Tensor]  # randomized model parameters, (nbatch, nvalues) each
    warned: np.ndarray  # (nbatch,) bool: MuJoCo raised a warning, or a control was bad
    rows_after: Optional[np.ndarray]  # continue_episodes: the state rows after this batch
    extras: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)  # policy's
    images: dict[str, torch.Tensor] = dataclasses.field(default_factory=dict)  # cameras'
    rendering: list = dataclasses.field(default_factory=list)  # futures filling `images`
    # terminate= with continue_episodes: (pending, episode steps) after this batch
    episodes: Optional[tuple[np.ndarray, np.ndarray]] = None


class CpuBackend(Backend):
    """`backend="cpu"`."""

    counting_warnings = False  # MuJoCo's warnings counted for this backend (see __init__)

    def __init__(self, config, shard, stats):
        super().__init__(config, shard, stats)
        c = config
        self.nthread = threads.threads_per_worker(
            shard, c.nthread, c.torch_threads,
            trains_on_cpu=c.device is None or c.device.type == "cpu")
        self.batch = mj_batch.Batch(c.model, c.nbatch, nthread=self.nthread)
        if c.models is not None:
            self.batch.set_models(c.models)
        # randomized fields: live per-simulation values, flattened per simulation
        self.expanded = {} if c.randomization is None else {
            r.field: self.batch.expand(r.field).reshape(c.nbatch, -1)
            for r in c.randomization.resolved}
        # which trajectories start afresh, the variant and values each runs with
        self.trajectories = Trajectories(c)
        # per model (of the list, or variant): each row as mj_resetData leaves it (user
        # inputs, zero warmstart), the undriven control columns, and with variants the
        # initial states that come from the model; `trajectories.per_trajectory` picks them.
        # The range MuJoCo clamps each control column to, per model (the delivered control is
        # what acted)
        tables = c.model_tables(layout.INTEGRATION)
        self.reset_rows, self.control_defaults = tables.reset_rows, tables.control_defaults
        self.variant_states, self.ctrl_bounds = tables.variant_states, (tables.low, tables.high)
        self.physics_cols = layout.component_columns(c.model, layout.INTEGRATION,
                                                     layout.FULLPHYSICS)
        self.pin = c.device is not None and c.device.type == "cuda"
        # live counters, (nbatch, mjNWARNING); zeroed before every batch, as mujoco.rollout
        # does: mj_resetData, which MuJoCo calls on an unstable simulation, zeroes them and
        # counts the new warning from 0, so a counter already at 1 would not rise again
        self.warnings = self.batch.warning[:, :, 1]
        self.driver = drivers.driver(c, self.batch)  # the open or the closed loop
        # terminate=: the rules checked at every frame, and the autoreset
        self.episodes = (cpu_episodes.Episodes(c, self.batch, drivers.LiveSources(self.batch, c))
                         if c.terminate is not None else None)
        self.driver.episodes = self.episodes
        # cameras: rendered by a pool of renderer threads from recorded state rows
        self.images = [o for o in c.observations if o.rendered]
        self.renderer = (cpu_render.RenderPool(c.model, self.images, self.nthread)
                         if self.images else None)
        # last, so that a backend that failed to build holds nothing: counted and
        # summarised, not a line per diverged trajectory, until `close` gives it back
        mujoco_warnings.install()
        self.counting_warnings = True

    def produce(self, index: int) -> _Produced:
        c, t = self.config, self.trajectories
        rows = self.batch.state
        initial_t, initial = handoff.host_buffer((c.nbatch, c.nstate), pin=self.pin)
        if self.episodes is not None:
            self.episodes.start(self._fresh_rows(index), t.fresh.copy())
        if t.fresh.any():
            x0 = c.initial.sample(self.seed(index, seeds.INITIAL), c.nbatch)
            fresh = np.flatnonzero(t.fresh)
            t.take(self.draw_models(index))
            self._apply_params(fresh)
            rows[fresh] = t.per_trajectory(self.reset_rows)[fresh]
            if self.variant_states is not None:
                x0 = t.per_trajectory(self.variant_states)
            rows[np.ix_(fresh, self.physics_cols)] = x0[fresh]
        initial[...] = rows[:, self.physics_cols]

        # a new buffer per batch, also for a fixed array: a consumer may edit its batch
        control_t, control = handoff.host_buffer((c.nbatch, c.nstep, c.ncontrol), pin=self.pin)
        low, high = self._ctrl_bounds()
        run = self.driver.prepare(self.seed(index, seeds.CONTROL),
                                  t.per_trajectory(self.control_defaults), control, low, high)

        recorded = {}  # one buffer per source, shared by the observations that read it
        sources = [(*recorded_from.source(o), o.dtype) for o in c.observations
                   if not o.rendered]
        if self.images:  # what rendering a frame needs: the state rows
            sources.append((layout.INTEGRATION, (self.batch.nstate,), np.dtype(np.float64)))
        for source, shape, dtype in sources:
            if source not in recorded:
                recorded[source] = handoff.host_buffer(
                    (c.nbatch, c.nframes, *shape), handoff.torch_dtype(dtype), pin=self.pin)
        self.warnings[...] = 0
        start = time.perf_counter()
        out = {s: array for s, (_, array) in recorded.items()}
        bad_control, extras = run(out)
        self.stats.add(simulate_s=time.perf_counter() - start)
        if self.episodes is not None:
            self.episodes.unapplied(control)
            extras = {**extras, **{k: torch.from_numpy(v)
                                   for k, v in self.episodes.flags.items()}}
        warned = self.warnings.any(axis=1) | bad_control
        if c.continue_episodes:
            # the rows the next batch continues from: a trajectory restarts there when MuJoCo
            # reset it (its warning), it got a bad control, or it recorded a non-finite value
            # (what `deliver` flags too), so this check cannot wait for the hand-off
            warned |= ~_finite([tensor for tensor, _ in recorded.values()], c.nbatch)
        # a diverged trajectory restarts from a fresh initial state
        t.finished(warned)
        rows_after = rows.copy() if c.continue_episodes else None
        params = {k: torch.from_numpy(v.copy()) for k, v in t.params.items()}
        images, rendering = {}, []
        if self.images:
            images = {o.key: handoff.host_buffer((c.nbatch, c.nframes, *o.shape),
                                                 handoff.torch_dtype(o.dtype), pin=self.pin)
                      for o in self.images}
            rendering = self.renderer.render(recorded[layout.INTEGRATION][1], self._model_of(),
                                             {k: a for k, (_, a) in images.items()})
        episodes = (None if self.episodes is None or not c.continue_episodes else
                    (self.episodes.pending.copy(), self.episodes.episode_steps.copy()))
        return _Produced({s: tensor for s, (tensor, _) in recorded.items()}, control_t, initial_t,
                         params, warned, rows_after, extras,
                         {k: t for k, (t, _) in images.items()}, rendering, episodes)

    def _fresh_rows(self, index: int):
        """`episodes.FreshRows` of batch `index`: each row's fresh initial state after a reset,
        from its initial-state source (a generator's `fresh_draw`s), as the row of
        mj_resetData with zero warmstart."""
        c, t = self.config, self.trajectories

        draws: dict[int, np.ndarray] = {}  # a generator's sets of fresh states, drawn when needed

        def fresh(rows: np.ndarray, episodes: np.ndarray) -> np.ndarray:
            out = t.per_trajectory(self.reset_rows)[rows].copy()
            if c.initial.generator is not None:
                sets = episodes % terminate.FRESH_DRAWS
                for e in np.unique(sets):  # drawn when a reset first needs them
                    if e not in draws:
                        draws[e] = self.fresh_draw(index, int(e))
                x0 = np.stack([draws[e][r] for r, e in zip(rows, sets)])
            elif self.variant_states is not None:
                x0 = t.per_trajectory(self.variant_states)[rows]
            else:
                x0 = c.initial.fixed[rows]
            out[:, self.physics_cols] = x0
            return out
        return fresh

    def _model_of(self):
        """Trajectory i's model as it ran this batch, for the render threads (which run while
        the next batch redraws variants and randomized values: a snapshot of them)."""
        return cpu_render.ModelPool.of(self.config).model_of(
            {k: v.copy() for k, v in self.trajectories.params.items()})

    def _ctrl_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(nbatch, ncontrol) each: the range each trajectory's controls are clamped to."""
        c = self.config
        if "actuator_ctrlrange" in self.expanded:  # randomized: each trajectory's own
            return controls.applied_bounds([c.model], c.control_spec, self.expanded[
                "actuator_ctrlrange"].reshape(c.nbatch, c.model.nu, 2))
        return tuple(self.trajectories.per_trajectory(b) for b in self.ctrl_bounds)

    def _apply_params(self, rows: np.ndarray) -> None:
        """MuJoCo's batch runs trajectories `rows` with what `trajectories` says they run with
        (their variant's model, their randomized values) from now on."""
        c, params = self.config, self.trajectories.params
        if c.variants is not None:
            self.batch.set_models([c.variants[i] for i in params["variant"]])
        if c.randomization is None:
            return
        for r in c.randomization.resolved:
            self.expanded[r.field][np.ix_(rows, r.elements)] = params[r.param.key][rows]
        if c.randomization.setconst:  # constants MuJoCo derives from the changed fields
            self.batch.set_const(None if len(rows) == c.nbatch else rows)

    def deliver(self, p: _Produced) -> dict[str, torch.Tensor]:
        c = self.config
        for future in p.rendering:  # rendered while the next batch simulated
            future.result()
        # MuJoCo's checks catch NaN/Inf/huge in qpos, qvel and qacc; the records' check covers
        # every floating record and runs here, overlapped with the next batch's simulation
        # (continuing, `produce` made it already)
        diverged = (p.warned if c.continue_episodes
                    else p.warned | ~_finite(p.recorded.values(), c.nbatch))
        if diverged.any():
            mujoco_warnings.summarize(stacklevel=4)
        self.stats.add(batches=1, steps=c.nbatch * c.nstep, diverged=int(diverged.sum()))
        out = {o.key: recorded_from.select(o, p.recorded[recorded_from.source(o)[0]])
               for o in c.observations if not o.rendered}
        out.update(control=p.control, initial_state=p.initial_state, **p.extras)
        out = {k: handoff.to_target(v, c.device, c.dtype if v.is_floating_point() else None)
               for k, v in out.items()}
        out["diverged"] = handoff.to_target(torch.from_numpy(diverged), c.device, None)
        out.update({k: handoff.to_target(v, c.device, None) for k, v in p.images.items()})
        if p.params:
            out["params"] = {k: handoff.to_target(v, c.device, c.dtype if v.is_floating_point()
                                                  else None) for k, v in p.params.items()}
        return out

    def checkpoint(self, produced: _Produced) -> Optional[dict]:
        if not self.config.continue_episodes:
            return None
        encoded = self.trajectories.checkpoint(produced.rows_after, produced.warned,
                                               produced.params)
        if produced.episodes is not None:
            encoded["episodes"] = resume.encode_episodes(*produced.episodes)
        return encoded

    def restore(self, trajectories: dict) -> None:
        self.batch.state[...] = self.trajectories.restore(trajectories)
        if self.episodes is not None:
            self.episodes.pending, self.episodes.episode_steps = resume.decode_episodes(
                trajectories, self.config.nbatch)
        # the trajectories that continue run on the models they ran on
        self._apply_params(np.arange(self.config.nbatch))

    def close(self) -> None:
        # frees the batch's thread pool now rather than at garbage collection: every view of
        # its buffers (warnings, expanded fields, the closed loop's bound outputs) keeps the
        # native mujoco._batch.Batch, and its threads, alive
        self.batch = self.warnings = None
        if self.counting_warnings:  # closed twice: at exit and at the end
            self.counting_warnings = False
            mujoco_warnings.release()
        self.driver.close()
        self.expanded = {}
        if self.renderer is not None:
            self.renderer.close()


def _finite(recorded: Any, nbatch: int) -> np.ndarray:
    """(nbatch,) bool: every floating value each trajectory recorded (tensors (nbatch, ...))
    is finite (`rules.finite`, the frame check every engine makes)."""
    finite = rules.finite([t.numpy() for t in recorded if t.is_floating_point() and t.numel()],
                          np)
    return np.ones(nbatch, dtype=bool) if finite is None else finite
