"""Episodes that end on the Warp engine (`terminate=`), inside its captured step graph.

Every step, after the frame is recorded: the rules read the frame's own state (its positions,
and MuJoCo Warp's kinematics of them for body rules), the flags go into their frame, and at a
frame's end the trajectories that met a rule are set to their fresh state, so that the next
step starts from it. A fresh frame's steps run from that state with the inputs mj_resetData
leaves (what the frame records besides its state is the step's forward pass there, as the CPU
engine's mj_forward), and the state is held there after each step (physics and zero
warmstart). All device tensors and fixed buffers, so that one graph serves every step; the
batch's side (`start`, `finish`) runs outside it, on the engine's stream.
"""

from __future__ import annotations

from typing import Any

import torch

from simloader import terminate

_PHYSICS = ("time", "qpos", "qvel", "act")  # a FULLPHYSICS row, in order


class Episodes:
    """One engine's episode buffers and its per-step bookkeeping.

    Args:
      config: the engine's configuration (its `terminate` rules, sizes).
      views: torch views of MuJoCo Warp's data arrays, (nbatch, -1) each.
      kinematics: MuJoCo Warp's kinematics of the data now (for body rules), or None.
    """

    def __init__(self, config: Any, views: dict[str, torch.Tensor], kinematics: Any):
        c = config
        self.rules, self.every = c.terminate, c.record_every
        self.views, self.kinematics = views, kinematics
        like = views["qpos"]
        n, f = c.nbatch, dict(dtype=like.dtype, device=like.device)
        self.widths = [views[name].shape[1] for name in _PHYSICS]
        nstate = sum(self.widths)
        flags = dict(dtype=torch.bool, device=like.device)
        steps = dict(dtype=torch.int64, device=like.device)
        # carried between batches (continue_episodes): rows whose last frame met a rule, and
        # the steps of each episode so far
        self.pending = torch.zeros(n, **flags)
        self.steps = torch.zeros(n, **steps)
        # this batch's: rows whose frame now is a fresh state, that state, resets so far
        self.held = torch.zeros(n, **flags)
        self.at = torch.zeros((n, nstate), **f)
        self.resets = torch.zeros(n, **steps)
        self.rows = torch.arange(n, device=like.device)
        # each row's fresh states: its initial-state source's row (1 draw) or a generator's
        # FRESH_DRAWS draws of the batch; and the inputs as mj_resetData leaves them
        draws = terminate.FRESH_DRAWS if c.initial.generator is not None else 1
        self.fresh = torch.zeros((n, draws, nstate), **f)
        self.reset_control = torch.zeros((n, c.ncontrol), **f)
        self.flags = {k: torch.zeros((n, c.nframes), **flags)
                      for k in ("terminated", "truncated", "first")}

    # -- the batch's side (outside the graph, on the engine's stream) ------------------------

    def start(self, fresh: torch.Tensor, reset_control: torch.Tensor,
              starts_afresh: torch.Tensor) -> None:
        """Before a batch: its fresh states ((nbatch, draws, nstate)) and reset inputs
        ((nbatch, ncontrol)); rows that start afresh (`starts_afresh`) start a new episode;
        rows whose last frame met a rule start at their fresh state."""
        self.fresh.copy_(fresh)
        self.reset_control.copy_(reset_control)
        self.resets.zero_()
        self.pending &= ~starts_afresh
        self.steps.masked_fill_(starts_afresh, 0)
        self.held.copy_(self.pending)
        self._swap(self.pending)

    def finish(self, control: torch.Tensor) -> dict[str, torch.Tensor]:
        """After a batch: its flags (new tensors), and the control rows of its fresh frames
        set to NaN in `control` ((nbatch, nstep, ncontrol), the delivered rows)."""
        first = self.flags["first"]
        unapplied = first.repeat_interleave(self.every, dim=1)[..., None]
        control.masked_fill_(unapplied, float("nan"))
        return {k: v.clone() for k, v in self.flags.items()}

    # -- inside the graph --------------------------------------------------------------------

    def inputs(self, u: torch.Tensor) -> torch.Tensor:
        """The step's control rows: a held row's inputs stay as mj_resetData leaves them."""
        return torch.where(self.held[:, None], self.reset_control, u)

    def hold(self) -> None:
        """Held rows back at their fresh state after the step (state, zero warmstart)."""
        self._set_state(self.held, self.at)

    def after_step(self, t: torch.Tensor, frame: torch.Tensor) -> None:
        """After step `t` (of frame `frame`, both (1,)) was recorded: the episode's steps, the
        frame's flags, and at a frame's end the rows that met a rule set to their fresh
        state."""
        self.steps.copy_(torch.where(self.held, 0, self.steps + 1))
        fields = {}
        if "qpos" in self.rules.reads:
            fields["qpos"] = self.views["qpos"]
        if self.rules.kinematic:
            fields.update(self.kinematics())
        no = torch.zeros_like(self.held)
        terminated = self.rules.terminated(torch, fields, no)
        truncated = self.rules.truncated(self.steps, no, torch)
        for key, value in (("terminated", terminated), ("truncated", truncated),
                           ("first", self.held)):
            self.flags[key].index_copy_(1, frame, value[:, None])
        end = (t + 1) % self.every == 0  # (1,): this step ends its frame
        self.pending.copy_(torch.where(end, terminated | truncated, self.pending))
        self.held.copy_(torch.where(end, self.pending, self.held))
        self._swap(self.pending & end)

    def _swap(self, rows: torch.Tensor) -> None:
        """Rows `rows` ((nbatch,) bool) take their next fresh state (their reset's draw)."""
        draw = self.resets % self.fresh.shape[1]
        self.at.copy_(torch.where(rows[:, None], self.fresh[self.rows, draw], self.at))
        self.resets += rows
        self._set_state(rows, self.at)

    def _set_state(self, rows: torch.Tensor, state: torch.Tensor) -> None:
        start = 0
        for name, width in zip(_PHYSICS, self.widths):
            view = self.views[name]
            view.copy_(torch.where(rows[:, None], state[:, start:start + width], view))
            start += width
        warmstart = self.views["qacc_warmstart"]
        warmstart.masked_fill_(rows[:, None], 0.0)
