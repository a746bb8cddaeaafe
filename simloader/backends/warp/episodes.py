"""Episodes that end on the Warp engine (`terminate=`), inside its captured step graph.

Every step, after the frame is recorded: the rules read the frame's own state (its positions,
and MuJoCo Warp's kinematics of them for body rules) and the flags go into their frame. At the
next frame's first step, the trajectories whose frame met a rule are set to their fresh state
first (so a policy's observations after the ending frame show the ending state, as on the CPU
engine). A fresh frame's steps run from that state with the inputs mj_resetData
leaves (what the frame records besides its state is the step's forward pass there, as the CPU
engine's mj_forward), and the state is held there after each step (physics and zero
warmstart).

Two Warp kernels of its own do it, one thread per world (`_begin`, `_after_step`), and the engine's
fused kernels (`fused.py`) take the held worlds' inputs and hold them after each step, so that a
step adds two launches to the graph (plus the kinematics for body rules): on a cheap model every
launch shows (the cart-pole's step is a few hundred microseconds for 8192 worlds). They read the
rules as the table `terminate.Rule.row` spells them. The batch's side (`start`, `finish`) runs
outside the graph, on the engine's stream.
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp

from simloader import terminate

_PHYSICS = ("time", "qpos", "qvel", "act")  # a FULLPHYSICS row, in order
OUTSIDE, BELOW, TILTED = (terminate.KINDS[k] for k in ("outside", "below", "tilted"))
# the rule kinds `_after_step` has a branch for (a row of another kind would be met never)
EVALUATED = {OUTSIDE: "outside", BELOW: "below", TILTED: "tilted"}


@wp.func
def set_state(w: int, at: wp.array2d(dtype=wp.float32), time: wp.array(dtype=wp.float32),
              qpos: wp.array2d(dtype=wp.float32), qvel: wp.array2d(dtype=wp.float32),
              act: wp.array2d(dtype=wp.float32), warmstart: wp.array2d(dtype=wp.float32)):
    """World `w` at its fresh state `at[w]` (time, qpos, qvel, act), zero warmstart."""
    nq, nv, na = qpos.shape[1], qvel.shape[1], act.shape[1]
    time[w] = at[w, 0]
    for i in range(nq):
        qpos[w, i] = at[w, 1 + i]
    for i in range(nv):
        qvel[w, i] = at[w, 1 + nq + i]
        warmstart[w, i] = 0.0
    for i in range(na):
        act[w, i] = at[w, 1 + nq + nv + i]


@wp.kernel
def _after_step(t: wp.array(dtype=wp.int64), every: int, time_limit: int,
                kinds: wp.array(dtype=wp.int32), index: wp.array(dtype=wp.int32),
                a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32),
                xpos: wp.array2d(dtype=wp.vec3), xmat: wp.array2d(dtype=wp.mat33),
                held: wp.array(dtype=wp.bool), pending: wp.array(dtype=wp.bool),
                steps: wp.array(dtype=wp.int64),
                terminated: wp.array2d(dtype=wp.bool), truncated: wp.array2d(dtype=wp.bool),
                first: wp.array2d(dtype=wp.bool), qpos: wp.array2d(dtype=wp.float32)):
    """After step `t[0]` was recorded: the episode's steps, the frame's flags, and at a
    frame's end which worlds met a rule (`pending`: the next frame holds them at their fresh
    state)."""
    w = wp.tid()
    step = t[0]
    if held[w]:
        steps[w] = wp.int64(0)
    else:
        steps[w] = steps[w] + wp.int64(1)
    met = bool(False)  # dynamic: set inside the loop
    for r in range(kinds.shape[0]):
        i = index[r]
        if kinds[r] == OUTSIDE:
            q = qpos[w, i]
            if q < a[r] or q > b[r]:
                met = True
        elif kinds[r] == BELOW:
            if xpos[w, i][2] < a[r]:
                met = True
        elif kinds[r] == TILTED:
            if xmat[w, i][2, 2] < a[r]:
                met = True
    limit = time_limit > 0 and steps[w] >= wp.int64(time_limit)
    frame = int(step // wp.int64(every))
    terminated[w, frame] = met
    truncated[w, frame] = limit
    first[w, frame] = held[w]
    if (step + wp.int64(1)) % wp.int64(every) == wp.int64(0):  # the frame ends here
        pending[w] = met or limit


@wp.kernel
def _begin(t: wp.array(dtype=wp.int64), every: int, pending: wp.array(dtype=wp.bool),
           held: wp.array(dtype=wp.bool), fresh: wp.array3d(dtype=wp.float32),
           resets: wp.array(dtype=wp.int64), at: wp.array2d(dtype=wp.float32),
           time: wp.array(dtype=wp.float32), qpos: wp.array2d(dtype=wp.float32),
           qvel: wp.array2d(dtype=wp.float32), act: wp.array2d(dtype=wp.float32),
           warmstart: wp.array2d(dtype=wp.float32)):
    """Before step `t[0]`: at a frame's first step, the worlds whose last frame met a rule
    (`pending`) are held this frame, at their next fresh state."""
    w = wp.tid()
    if t[0] % wp.int64(every) == wp.int64(0):
        held[w] = pending[w]
        if pending[w]:
            draw = int(resets[w] % wp.int64(fresh.shape[1]))
            for c in range(at.shape[1]):
                at[w, c] = fresh[w, draw, c]
            resets[w] = resets[w] + wp.int64(1)
            set_state(w, at, time, qpos, qvel, act, warmstart)


def check_rules(rules: Any) -> None:
    """Refuses, at construction, a rule (`terminate.Episodes.rules`) of a kind `_after_step`
    does not evaluate: it would never end an episode on this engine.

    Raises:
      ValueError: naming the rule and its kind.
    """
    kinds = ", ".join(f"{name} ({kind})" for kind, name in EVALUATED.items())
    for rule in rules.rules:
        try:
            kind = rule.row()[0]
        except NotImplementedError:  # a rule of the user's own, with `met` alone
            kind = None
        if kind not in EVALUATED:
            raise ValueError(f"terminate: {rule!r}: its kind (`row()[0]`: {kind}) is none the "
                             f"Warp engine's kernel evaluates: {kinds}; use backend='cpu' or "
                             f"'mjx'")


class Episodes:
    """One engine's episode buffers and its per-step kernels.

    Args:
      config: the engine's configuration (its `terminate` rules, sizes).
      d: MuJoCo Warp's data (its arrays never move).
      kinematics: MuJoCo Warp's kinematics of the data now (for body rules), or None.
      device: the torch device of the data.
    """

    def __init__(self, config: Any, d: Any, kinematics: Any, device: torch.device):
        c = config
        self.rules, self.every, self.d = c.terminate, c.record_every, d
        self.kinematics = kinematics if c.terminate.kinematic else None
        self.time_limit = c.terminate.time_limit or 0
        n = c.nbatch
        nstate = 1 + c.model.nq + c.model.nv + c.model.na
        f32 = dict(dtype=torch.float32, device=device)
        flags = dict(dtype=torch.bool, device=device)
        steps = dict(dtype=torch.int64, device=device)
        table = [r.row() for r in c.terminate.rules]  # empty with a time limit alone
        self.kinds = torch.tensor([r[0] for r in table], dtype=torch.int32, device=device)
        self.index = torch.tensor([r[1] for r in table], dtype=torch.int32, device=device)
        self.a = torch.tensor([r[2] for r in table], **f32)
        self.b = torch.tensor([r[3] for r in table], **f32)
        # carried between batches (continue_episodes): worlds whose last frame met a rule,
        # and the steps of each episode so far
        self.pending = torch.zeros(n, **flags)
        self.steps = torch.zeros(n, **steps)
        # this batch's: worlds whose frame now is a fresh state, that state, resets so far
        self.held = torch.zeros(n, **flags)
        self.at = torch.zeros((n, nstate), **f32)
        self.resets = torch.zeros(n, **steps)
        # each world's fresh states: its initial-state source's row (1 draw) or a generator's
        # FRESH_DRAWS draws of the batch; and the inputs as mj_resetData leaves them
        draws = terminate.FRESH_DRAWS if c.initial.generator is not None else 1
        self.fresh = torch.zeros((n, draws, nstate), **f32)
        self.reset_control = torch.zeros((n, c.ncontrol), **f32)
        self.flags = {k: torch.zeros((n, c.nframes), **flags)
                      for k in ("terminated", "truncated", "first")}
        self.state = [getattr(d, name) for name in (*_PHYSICS, "qacc_warmstart")]
        self.w = {k: wp.from_torch(v) for k, v in (
            ("kinds", self.kinds), ("index", self.index), ("a", self.a), ("b", self.b),
            ("fresh", self.fresh), ("held", self.held), ("pending", self.pending),
            ("steps", self.steps), ("resets", self.resets), ("at", self.at))}
        self.w.update({k: wp.from_torch(v) for k, v in self.flags.items()})

    # -- the batch's side (outside the graph, on the engine's stream) ------------------------

    def start(self, fresh: torch.Tensor, reset_control: torch.Tensor,
              starts_afresh: torch.Tensor) -> None:
        """Before a batch: its fresh states ((nbatch, draws, nstate)) and reset inputs
        ((nbatch, ncontrol)); worlds that start afresh (`starts_afresh`) start a new episode;
        worlds whose last frame met a rule stay pending (the first step holds them at their
        fresh state)."""
        self.fresh.copy_(fresh)
        self.reset_control.copy_(reset_control)
        self.resets.zero_()
        self.pending &= ~starts_afresh
        self.steps.masked_fill_(starts_afresh, 0)
        self.held.zero_()

    def finish(self, control: torch.Tensor) -> dict[str, torch.Tensor]:
        """After a batch: its flags (new tensors), and the control rows of its fresh frames
        set to NaN in `control` ((nbatch, nstep, ncontrol), the delivered rows)."""
        unapplied = self.flags["first"].repeat_interleave(self.every, dim=1)[..., None]
        control.masked_fill_(unapplied, float("nan"))
        return {k: v.clone() for k, v in self.flags.items()}

    # -- inside the graph --------------------------------------------------------------------

    def begin(self, t: Any) -> None:
        """Before step `t` (the engine's (1,) int64 Warp array): at a frame's first step,
        the worlds whose last frame met a rule take their fresh state and are held there this
        frame."""
        w = self.w
        wp.launch(_begin, dim=len(self.held), inputs=[
            t, self.every, w["pending"], w["held"], w["fresh"], w["resets"],
            w["at"], *self.state])

    def external(self, met: torch.Tensor, frame: int) -> None:
        """A callable's verdict on frame `frame` ((nbatch,) bool), after its last step: the
        frame is terminated where it says so, and the next frame is fresh there."""
        self.flags["terminated"][:, frame] |= met
        self.pending |= met

    def after_step(self, t: Any) -> None:
        """After step `t` (the engine's (1,) int64 Warp array) was recorded: the episode's
        steps, the frame's flags, and at a frame's end which worlds met a rule (`pending`)."""
        if self.kinematics is not None:
            self.kinematics()
        w, d = self.w, self.d
        wp.launch(_after_step, dim=len(self.held), inputs=[
            t, self.every, self.time_limit, w["kinds"], w["index"], w["a"],
            w["b"], d.xpos, d.xmat, w["held"], w["pending"], w["steps"], w["terminated"],
            w["truncated"], w["first"], d.qpos])
