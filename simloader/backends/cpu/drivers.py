"""The CPU backend's two drivers, chosen once per backend: the open loop (controls known before
the batch; `mujoco.batch` runs every step in C) and the closed loop (a torch policy picks each
step's controls; one `Batch.step` per step). Both fill the batch's delivered `control` buffer
with the rows as they acted and record into the same buffers, so the backend around them is
one. Each takes what it reads as arguments and says what it writes (in, out), as MuJoCo Warp
marks its kernels' arrays; a driver holds only the configuration and MuJoCo's batch."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Optional

import mujoco
import numpy as np
import torch
from mujoco import batch as mj_batch

from simloader import controls, handoff, layout, policy, rules
from simloader.backends import policy_loop
from simloader.backends.cpu import recorded

# run(out) -> (bad, extras): simulates the batch into `out` ({source: (nbatch, nframes, ...)});
# bad: (nbatch,) bool, a trajectory got a bad (non-finite or absurd) control; extras: tensors
# delivered beside the batch (the policy's)
Run = Callable[[dict], tuple[np.ndarray, dict[str, torch.Tensor]]]


class OpenLoop:
    """Generated, fixed or absent (`control=None`) controls, all known before the batch."""

    def __init__(self, config: Any, batch: mj_batch.Batch):
        self.config, self.batch = config, batch
        self.episodes: Optional[Any] = None  # `episodes.Episodes` with terminate=, set by the backend
        # record_kinematics="frame": the frame's step is `Batch.step` with the forward stages
        # at the new state, and the frame is read from the sources MuJoCo keeps current
        self.live = LiveSources(batch, config) if config.frame_stage is not None else None

    def prepare(self, seed: np.random.SeedSequence, defaults: np.ndarray, control: np.ndarray,
                low: np.ndarray, high: np.ndarray) -> Run:
        """In: the batch's control `seed`, `defaults` (nbatch, ncontrol) each trajectory's
        undriven control columns, `low`, `high` (nbatch, ncontrol) the clamp bounds. Out:
        `control` ((nbatch, nstep, ncontrol)) filled with the rows as MuJoCo applies them;
        returns the run."""
        c = self.config
        if c.control.fixed is not None:
            control[...] = c.control.fixed
        elif c.control.random:
            c.control.sample_numpy(seed, control, defaults)
        else:
            # control=None: the inputs stay as mj_resetData left them (in the rows), for every
            # step; delivered as such
            control[...] = defaults[:, None]
        control[...], bad = controls.as_applied(control, low[:, None], high[:, None])
        applied = control if c.control.fixed is not None or c.control.random else None

        def run(out: dict) -> tuple[np.ndarray, dict[str, torch.Tensor]]:
            self._rollout(applied, out)
            return bad, {}
        return run

    def _rollout(self, control: Optional[np.ndarray], out: dict) -> None:
        """Runs the batch's `nstep` steps, recording the sources into `out` after every
        `record_every`-th step.

        With `record_every=k > 1`, each frame is `k - 1` steps recording nothing and one step
        recording into a one-frame buffer, copied into its frame: the state rows (warmstart
        included) carry the trajectory from call to call, so the steps are those of one call.
        With `record_kinematics="frame"`, the frame's step is `Batch.step` computing the
        forward stages at the new state (`frame_stage`), read from the live sources.
        """
        c, k, batch = self.config, self.config.record_every, self.batch
        items = tuple(out)
        if k == 1 and self.episodes is None and self.live is None:
            batch.rollout(c.nstep, control, control_spec=c.control_spec, record=items, out=out)
            return
        if control is not None:
            control = np.broadcast_to(control, (c.nbatch, c.nstep, c.ncontrol))
        frame = {s: np.empty((c.nbatch, 1, *a.shape[2:]), a.dtype) for s, a in out.items()}
        episodes = self.episodes
        for j in range(c.nframes):
            # with terminate=: the trajectories whose frame j is a fresh initial state
            reset = episodes.before_frame() if episodes is not None else None
            u = None if control is None else control[:, j * k:(j + 1) * k]
            if k > 1:
                batch.rollout(k - 1, None if u is None else u[:, :-1],
                              control_spec=c.control_spec, record=())
            if self.live is None:
                batch.rollout(1, None if u is None else u[:, -1:],
                              control_spec=c.control_spec, record=items, out=frame)
            else:
                if u is not None:  # as rollout applies a row: its components into the state
                    batch.state[:, self.live.control_columns] = u[:, -1]
                batch.step(stage=c.frame_stage)
                self.live.record(frame, 0)
            if episodes is not None:
                episodes.after_frame(reset, frame, j)
            for s, a in out.items():
                a[:, j] = frame[s][:, 0]

    def close(self) -> None:
        # they keep MuJoCo's native batch (and its threads) alive
        self.batch = self.live = None


class ClosedLoop:
    """A torch policy picks every step's controls, from observations of the state now."""

    def __init__(self, config: Any, batch: mj_batch.Batch):
        self.config, self.batch = config, batch
        self.snapshot = policy.Snapshot(config.policy)
        self.live: Optional[LiveSources] = None  # made at the first batch
        self.episodes: Optional[Any] = None  # `episodes.Episodes` with terminate=, set by the backend

    def prepare(self, seed: np.random.SeedSequence, defaults: np.ndarray, control: np.ndarray,
                low: np.ndarray, high: np.ndarray) -> Run:
        """In: the batch's control `seed` (its policy noise; `defaults` unused: the noise's
        undriven columns are 0), `low`, `high` the clamp bounds. Takes the weights the batch
        runs with (one version of them, a copy taken now). Out: the run fills `control` step
        by step with the rows as they acted."""
        act, version = self.snapshot.take()
        control[...] = 0.0

        def run(out: dict) -> tuple[np.ndarray, dict[str, torch.Tensor]]:
            return self._steps(seed, control, low, high, out, act, version)
        return run

    def _steps(self, seed: np.random.SeedSequence, control: np.ndarray, low: np.ndarray,
               high: np.ndarray, out: dict, act: Any,
               version: int) -> tuple[np.ndarray, dict[str, torch.Tensor]]:
        """Runs the batch's `nstep` steps (`policy_loop.run`), recording the sources into
        `out` as the open loop.

        Each step: the policy's rows, plus noise, clamped as MuJoCo clamps, go into the rows'
        `control_spec` components; one `mj_step` per trajectory (`Batch.step`); the next
        observations are views of the state rows and of the fields the batch binds, which
        MuJoCo refreshes after every call. The first observations are those of the initial
        state, derived fields by `mj_forward`.
        """
        c, b, k = self.config, self.batch, self.config.record_every
        if self.live is None:
            self.live = LiveSources(b, c)
        live = self.live
        noise = None
        if c.policy_noise is not None:
            noise = np.empty((c.nbatch, c.nstep, c.ncontrol))
            c.policy_noise.sample_numpy(seed, noise, c.policy_noise.default_rows)
        bad = np.zeros(c.nbatch, dtype=bool)
        episodes = self.episodes
        held = np.zeros(0, dtype=np.intp)  # with terminate=: the rows whose frame is fresh
        stage = (int(mujoco.mjtStage.mjSTAGE_NONE) if c.frame_stage is None
                 else c.frame_stage)

        def step(rows: torch.Tensor, t: int) -> dict[str, torch.Tensor]:
            nonlocal held
            row = control[:, t]
            row[...] = rows.to(torch.float64).numpy()
            if noise is not None:
                row += noise[:, t]
            row[...], bad_now = controls.as_applied(row, low, high)
            bad[...] |= bad_now
            if episodes is not None and t % k == 0:  # a frame starts: its fresh rows
                held = episodes.before_frame()
            b.state[:, live.control_columns] = row
            if len(held):  # a fresh frame's inputs are mj_resetData's, not the policy's
                b.state[np.ix_(held, live.control_columns)] = \
                    episodes.reset_to[:, live.control_columns]
            # record_kinematics="frame": the stages at the new state, for every step's
            # observations and frames (mjSTAGE_NONE: none)
            b.step(stage=stage)
            if rules.frame_due(t, k):
                frame = rules.frame_index(t, k)
                live.record(out, frame)
                if episodes is not None:  # the fresh rows' frames, the rules, the resets
                    return episodes.after_frame(held, {s: a[:, frame:frame + 1]
                                                       for s, a in out.items()}, frame,
                                                observe=True)
            return live.observations()

        b.forward()
        extras = policy_loop.run((act, version), c, live.observations(), step,
                                 torch.device("cpu"))
        return bad, extras

    def close(self) -> None:
        # its bound outputs, and the batch, keep the native batch (and its threads) alive
        self.live = self.batch = None


def driver(config: Any, batch: mj_batch.Batch) -> Any:
    """The driver of `config` over MuJoCo's `batch`: the closed loop with a policy, else the
    open loop."""
    return (ClosedLoop if policy_loop.chosen(config) else OpenLoop)(config, batch)


class LiveSources:
    """The closed loop's view of the batch: every recorded source as MuJoCo keeps it current,
    `(nbatch, ...)`: state components as columns of the state rows, other fields as
    `Batch.bind` outputs (refreshed after every call, as `mj_step` leaves them)."""

    def __init__(self, batch: mj_batch.Batch, config):
        c = self.config = config
        self.batch = batch
        self.bound: dict = {}  # source -> live (nbatch, *source_shape) output
        self.columns: dict = {}  # source (an mjtState spec) -> its columns of the state rows
        # each record with its source, found once (observations() runs every step)
        # (rendered images are drawn from the state rows, not read from MjData)
        self.sources = [(o, *recorded.source(o)) for o in c.observations if not o.rendered]
        for _, source, shape in self.sources:
            if isinstance(source, str):
                self.bound[source] = batch.bind(source).reshape(c.nbatch, *shape)
            else:
                self.columns[source] = layout.component_columns(c.model, layout.INTEGRATION,
                                                                source)
        self.control_columns = layout.component_columns(c.model, layout.INTEGRATION,
                                                        c.control_spec)

    def value(self, source) -> np.ndarray:
        """The source's current values, `(nbatch, *source_shape)`; a view where MuJoCo's
        memory is laid out so, else a copy."""
        if source in self.bound:
            return self.bound[source]
        if source not in self.columns:  # a state spec no record reads (the cameras' rows)
            self.columns[source] = layout.component_columns(self.config.model,
                                                            layout.INTEGRATION, source)
        return self.batch.state[:, self.columns[source]]

    def observations(self) -> dict[str, torch.Tensor]:
        """The policy's observations now: a tensor of its own per key (the next step
        overwrites MuJoCo's buffers; a copy of this size costs little next to a policy
        call)."""
        out = {}
        for o, source, _ in self.sources:
            value = torch.tensor(self.value(source), dtype=handoff.torch_dtype(o.dtype))
            out[o.key] = recorded.select(o, value[:, None])[:, 0]
        return out

    def record(self, out: dict, frame: int) -> None:
        """Writes frame `frame` of every source into `out` ({source: (nbatch, nframes,
        ...)})."""
        for source, buffer in out.items():
            buffer[:, frame] = self.value(source)
