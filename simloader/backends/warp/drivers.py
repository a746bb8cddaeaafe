"""The Warp engine's two drivers, chosen once per engine: the open loop (a batch's control rows
known before it: drawn on the device, fixed, or the model's defaults; checked and clamped for
the whole batch at once; one graph replay per step) and the closed loop (a torch policy picks
each step's rows; the step graph adds the policy's noise, checks and clamps the rows and keeps
them as they acted).

Each driver has two sides. `rows` is the engine's, fixed when the engine is built (its graph
reads the buffers the driver allocates): the step's control row inside the graph, the batch's
start, the rows as they acted. `prepare` and `run` are a batch's, called by the backend inside
`Engine.queued` with the backend's seeds, tables and (closed loop) the weights its
`policy.Snapshot` took before, outside the lock (a copy of the weights may wait for a training
update).
"""

from __future__ import annotations

from typing import Any, Optional

import torch

from simloader import controls, seeds
from simloader.backends import policy_loop


class OpenLoop:
    """Rows known before the batch, in one (nbatch, nstep, ncontrol) buffer the graph reads."""

    observes = False  # no policy reads the step's observations

    def __init__(self, engine: Any):
        c = engine.config
        like = engine.views["qpos"]
        self.engine = engine
        self.controls = torch.zeros((c.nbatch, c.nstep, c.ncontrol), dtype=like.dtype,
                                    device=like.device)
        self.fixed: Optional[torch.Tensor] = None  # an explicit control array, on the device

    # -- the engine's side (fixed buffers, read by the graph) --------------------------------

    def row(self) -> torch.Tensor:
        """Step `t`'s rows, (nbatch, ncontrol), checked and clamped already (`start`)."""
        return self.controls.index_select(1, self.engine.t)[:, 0]

    def start(self) -> None:
        """The batch's rows checked and clamped at once, as the CPU backend does (fewer
        kernels per step)."""
        e = self.engine
        applied, bad = controls.as_applied(self.controls, e.low[:, None], e.high[:, None], torch)
        e.diverged |= bad
        self.controls.copy_(applied)

    def applied(self) -> torch.Tensor:
        """(nbatch, nstep, ncontrol): the rows as they acted (a new tensor)."""
        return self.controls.clone()

    # -- a batch's side (the backend's draws) ------------------------------------------------

    def prepare(self, backend: Any, index: int) -> None:
        """Batch `index`'s rows into the buffer: drawn on the device (generators) or the
        explicit array, with each trajectory's model defaults in the undriven columns. The
        engine's stream orders these writes after the previous batch's steps that read them."""
        c, tables = backend.config, backend.tables
        if c.control.fixed is not None:
            if self.fixed is None:
                self.fixed = backend.upload(c.control.fixed)
            self.controls.copy_(self.fixed)
            return
        defaults = backend.per_trajectory(tables.control_defaults)[:, None]
        self.controls.copy_(defaults.expand(self.controls.shape))
        if c.control.random:
            c.control.sample_torch(backend.seed(index, seeds.CONTROL), self.controls,
                                   tables.control_params)

    def run(self, backend: Any, taken: Any) -> dict[str, torch.Tensor]:
        """The batch's steps: one replay each. No extras (`taken`: None, no policy)."""
        for _ in range(backend.config.nstep):
            self.engine.advance()
        return {}


class ClosedLoop:
    """The policy's rows, one step at a time, into the (nbatch, ncontrol) buffer the graph
    reads; the graph keeps them, as they acted, in a (nbatch, nstep, ncontrol) buffer."""

    observes = True  # the policy reads each step's observations, images included

    def __init__(self, engine: Any):
        c = engine.config
        like = engine.views["qpos"]
        self.engine = engine
        f = dict(dtype=like.dtype, device=like.device)
        self.u = torch.zeros((c.nbatch, c.ncontrol), **f)  # the policy's rows of this step
        self.noise = (torch.zeros((c.nbatch, c.nstep, c.ncontrol), **f)
                      if c.policy_noise is not None else None)
        self.control = torch.empty((c.nbatch, c.nstep, c.ncontrol), **f)  # as they acted

    # -- the engine's side -------------------------------------------------------------------

    def row(self) -> torch.Tensor:
        """Step `t`'s rows: the policy's, plus its noise, flagged and clamped, kept."""
        e = self.engine
        u = self.u
        if self.noise is not None:
            u = u + self.noise.index_select(1, e.t)[:, 0]
        u, bad = controls.as_applied(u, e.low, e.high, torch)
        e.diverged |= bad
        self.control.index_copy_(1, e.t, u[:, None])
        return u

    def start(self) -> None:
        return None

    def applied(self) -> torch.Tensor:
        return self.control.clone()

    # -- a batch's side ----------------------------------------------------------------------

    def prepare(self, backend: Any, index: int) -> None:
        """The batch's policy noise, drawn as controls are (undriven columns 0); the stream
        waits for the weights' copy, which `policy.Snapshot.take` queued on the default
        stream."""
        c = backend.config
        if self.engine.gpu:
            self.engine.stream.wait_stream(torch.cuda.default_stream(backend.device))
        if self.noise is not None:
            self.noise.zero_()
            c.policy_noise.sample_torch(backend.seed(index, seeds.CONTROL), self.noise,
                                        backend.tables.noise_params)

    def run(self, backend: Any, taken: tuple[Any, int]) -> dict[str, torch.Tensor]:
        """The batch's steps (`policy_loop.run`; `taken`: the weights' copy and their
        version): the policy's rows into the graph's input, one replay each. Nothing waits on
        the host. Returns the policy's extras."""
        e = self.engine

        def step(rows: torch.Tensor, t: int) -> dict[str, torch.Tensor]:
            self.u.copy_(rows)
            e.advance()
            # the observations are views of MuJoCo Warp's arrays (or the graph's outputs),
            # which the next step rewrites: the policy keeps copies of its own
            return {k: v.clone() for k, v in e.obs.items()}

        return policy_loop.run(taken, backend.config, e.observe_now(), step, backend.device)


def driver(engine: Any) -> Any:
    """The engine's driver: the closed loop with a policy, else the open loop."""
    return ClosedLoop(engine) if policy_loop.chosen(engine.config) else OpenLoop(engine)
