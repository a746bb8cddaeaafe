"""Episodes that end on the CPU engine (`terminate=`): the rules checked at every recorded
frame, and the autoreset of the trajectories whose frame met one.

A batch with `terminate=` steps frame by frame (`record_every` steps each, as MuJoCo's batch
steps them). After a frame whose state met a rule, the trajectory's next frame is a fresh
initial state (its row of the initial-state source: the fixed state, or the generator's draw
seeded by batch, row and episode), with the inputs and zero warmstart `mj_resetData` leaves;
its `record_every` control rows are not applied (delivered as NaN), and what it records
besides the state is what `mj_forward` computes at that state (the observation of the fresh
state). Every other frame is `record_every` physics steps from the frame before it, exactly as
`mujoco.rollout` makes it, so every episode of a batch equals `mujoco.rollout` from its
initial state with its controls, bit for bit.

The rules read the frame's own state: its positions from the state rows, and what
`mj_kinematics` derives from them (xpos, xmat) by a position-stage forward of the batch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Optional

import mujoco
import numpy as np
import torch

from simloader import layout

# (rows, episodes) -> (len(rows), nintegration): each row's fresh initial state for its
# `episodes[i]`-th reset of the batch, as an mjSTATE_INTEGRATION row (inputs and warmstart as
# mj_resetData leaves them)
FreshRows = Callable[[np.ndarray, np.ndarray], np.ndarray]


class Episodes:
    """One batch's episode bookkeeping and autoreset, over MuJoCo's batch.

    Args:
      config: the dataset's configuration (its `terminate` rules, sizes).
      batch: MuJoCo's batch of the trajectories.
      live: the batch's sources as MuJoCo keeps them current (`drivers.LiveSources`).
    """

    def __init__(self, config: Any, batch: Any, live: Any):
        self.config, self.batch, self.live = config, batch, live
        self.rules = config.terminate
        self.qpos_columns = layout.component_columns(config.model, layout.INTEGRATION,
                                                     int(mujoco.mjtState.mjSTATE_QPOS))
        # the kinematics the rules read, registered now: MuJoCo's batch refreshes a bound
        # output after each call made once it is bound
        self.kinematics = {name: batch.bind(name) for name in self.rules.reads if name != "qpos"}
        n = config.nbatch
        # carried between batches (continue_episodes): the trajectories whose last frame met
        # a rule (their next frame is a fresh state) and the steps of each episode so far
        self.pending = np.zeros(n, dtype=bool)
        self.episode_steps = np.zeros(n, dtype=np.int64)

    def start(self, fresh_rows: FreshRows, starts_afresh: np.ndarray) -> None:
        """Before a batch: new flags to fill (`flags`: {"terminated", "truncated", "first":
        (nbatch, nframes) bool}). Trajectories that start afresh (`starts_afresh`: from the
        batch's initial state) start a new episode."""
        c = self.config
        self.fresh_rows = fresh_rows
        self.resets = np.zeros(c.nbatch, dtype=np.int64)  # resets of each row in this batch
        self.pending &= ~starts_afresh
        self.episode_steps[starts_afresh] = 0
        self.flags = {k: np.zeros((c.nbatch, c.nframes), dtype=bool)
                      for k in ("terminated", "truncated", "first")}

    def before_frame(self) -> np.ndarray:
        """The rows whose frame now is a fresh initial state: their state rows are set to it
        (so that the physics stepped for every row starts from a valid state, then
        discarded). Returns them."""
        rows = np.flatnonzero(self.pending)
        if len(rows):
            self.reset_to = self.fresh_rows(rows, self.resets[rows])
            self.resets[rows] += 1
            self.batch.state[rows] = self.reset_to
        return rows

    def after_frame(self, rows: np.ndarray, frame: dict, index: int,
                    observe: bool = False) -> Optional[dict[str, torch.Tensor]]:
        """After frame `index` was stepped and recorded into `frame` ({source: (nbatch, 1,
        ...)}): the rows reset at it hold their fresh state and record what mj_forward
        computes there; then every row's frame is checked against the rules.

        Returns the observations a policy gets after this frame where asked (`observe`), or
        None: taken before the body rules' position-stage forward, which refreshes MuJoCo's
        bound outputs with the frame's own kinematics (and leaves later stages stale), so that
        a policy sees what it sees without rules."""
        c, batch, live, flags = self.config, self.batch, self.live, self.flags
        k = c.record_every
        if len(rows):
            batch.state[rows] = self.reset_to
            batch.forward(ids=rows)  # the observation of the fresh state
            for source, buffer in frame.items():
                buffer[rows, 0] = live.value(source)[rows]
            flags["first"][rows, index] = True
        obs = (live.observations() if observe or self.rules.check is not None else None)
        self.episode_steps += k
        self.episode_steps[rows] = 0
        fields = {}
        if "qpos" in self.rules.reads:
            fields["qpos"] = batch.state[:, self.qpos_columns]
        # kinematics of the frame's own state, not the step's start (with
        # record_kinematics="frame" the step computed them already)
        if self.rules.kinematic:
            if c.frame_stage is None:
                batch.forward(stage=mujoco.mjtStage.mjSTAGE_POS)
            fields.update(self.kinematics)
        like = np.zeros(c.nbatch, dtype=bool)
        terminated = self.rules.terminated(np, fields, like)
        if self.rules.check is not None:  # a callable over the observations a policy gets
            terminated |= self.rules.checked(obs, index, c.nbatch).numpy()
        truncated = self.rules.truncated(np, self.episode_steps, like)
        flags["terminated"][:, index] = terminated
        flags["truncated"][:, index] = truncated
        self.pending = terminated | truncated
        return obs if observe else None

    def unapplied(self, control: np.ndarray) -> None:
        """The control rows of the fresh frames were not applied: delivered as NaN."""
        first = self.flags["first"]
        if first.any():
            steps = np.repeat(first, self.config.record_every, axis=1)
            control[steps] = np.nan
