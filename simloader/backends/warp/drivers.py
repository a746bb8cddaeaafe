"""The Warp engine's two drivers, chosen once per engine: the open loop (a batch's control rows
known before it: drawn on the device, fixed, or the model's defaults; checked and clamped for
the whole batch at once; one graph replay per step) and the closed loop (a torch policy picks
each step's rows; the step graph adds the policy's noise, checks and clamps the rows and keeps
them as they acted).

Each driver has two sides, and each method says what it reads (in) and writes (out), as MuJoCo
Warp marks its kernels' arrays. The engine's side is fixed when the engine is built (its graph
reads the buffers the driver allocates): `row` (inside the graph), `start`, `applied`. The
batch's side is called by the backend inside `Engine.queued`: `prepare` with the batch's seed
and defaults, `run` with the weights its `policy.Snapshot` took before, outside the lock (a copy
of the weights may wait for a training update).
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np
import torch

from simloader import controls
from simloader.backends import policy_loop


class OpenLoop:
    """Rows known before the batch, in one (nbatch, nstep, ncontrol) buffer the graph reads."""

    observes = False  # no policy reads the step's observations

    def __init__(self, engine: Any):
        c = engine.config
        like = engine.views["qpos"]
        self.engine, self.nstep = engine, c.nstep
        f = dict(dtype=like.dtype, device=like.device)
        self.controls = torch.zeros((c.nbatch, c.nstep, c.ncontrol), **f)
        # an explicit control array, on the device once; else the generators and their
        # parameters (the engine's tables), drawn on the device per batch
        self.fixed = (torch.as_tensor(c.control.fixed, **f)
                      if c.control.fixed is not None else None)
        self.plan = c.control if c.control.random else None
        self.params = engine.tables.control_params

    # -- the engine's side (fixed buffers, read by the graph) --------------------------------

    def row(self, t: torch.Tensor, low: torch.Tensor,
            high: torch.Tensor) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """In: `t` the (1,) step index. Out: step `t`'s rows, (nbatch, ncontrol), checked and
        clamped already (`start`), and no flags."""
        return self.controls.index_select(1, t)[:, 0], None

    def start(self, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        """In: `low`, `high` (nbatch, ncontrol), the clamp bounds. Out: the batch's rows
        checked and clamped at once in the buffer, as the CPU backend does (fewer kernels per
        step); returns the (nbatch,) flags of rows with a bad control."""
        applied, bad = controls.as_applied(self.controls, low[:, None], high[:, None], torch)
        self.controls.copy_(applied)
        return bad

    def applied(self) -> torch.Tensor:
        """Out: (nbatch, nstep, ncontrol), the rows as they acted (a new tensor)."""
        return self.controls.clone()

    # -- a batch's side ----------------------------------------------------------------------

    def prepare(self, seed: np.random.SeedSequence, defaults: torch.Tensor) -> None:
        """In: the batch's control `seed` and `defaults` (nbatch, ncontrol), each
        trajectory's undriven control columns. Out: the batch's rows in the buffer: the
        explicit array, or the defaults with the driven columns drawn on the device. The
        engine's stream orders these writes after the previous batch's steps that read
        them."""
        if self.fixed is not None:
            self.controls.copy_(self.fixed)
            return
        self.controls.copy_(defaults[:, None].expand(self.controls.shape))
        if self.plan is not None:
            self.plan.sample_torch(seed, self.controls, self.params)

    def run(self, taken: Any) -> dict[str, torch.Tensor]:
        """In: nothing (`taken`: None, no policy). Out: the batch's steps, one replay each;
        no extras."""
        for _ in range(self.nstep):
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

    def row(self, t: torch.Tensor, low: torch.Tensor,
            high: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """In: `t` the (1,) step index, `low`, `high` the clamp bounds, the policy's rows
        (`u`). Out: step `t`'s rows (plus noise, clamped; also kept as they acted) and the
        (nbatch,) flags of rows with a bad control."""
        u = self.u
        if self.noise is not None:
            u = u + self.noise.index_select(1, t)[:, 0]
        u, bad = controls.as_applied(u, low, high, torch)
        self.control.index_copy_(1, t, u[:, None])
        return u, bad

    def start(self, low: torch.Tensor, high: torch.Tensor) -> None:
        """Nothing to do: each step's rows are checked as they come."""
        return None

    def applied(self) -> torch.Tensor:
        """Out: (nbatch, nstep, ncontrol), the rows as they acted (a new tensor)."""
        return self.control.clone()

    # -- a batch's side ----------------------------------------------------------------------

    def prepare(self, seed: np.random.SeedSequence, defaults: torch.Tensor) -> None:
        """In: the batch's control `seed` (`defaults` unused: the noise's undriven columns
        are 0). Out: the batch's policy noise, drawn as controls are. The stream waits for
        the weights' copy, which `policy.Snapshot.take` queued on the default stream."""
        e, c = self.engine, self.engine.config
        if e.gpu:
            e.stream.wait_stream(torch.cuda.default_stream(e.device))
        if self.noise is not None:
            self.noise.zero_()
            c.policy_noise.sample_torch(seed, self.noise, e.tables.noise_params)

    def run(self, taken: tuple[Any, int]) -> dict[str, torch.Tensor]:
        """In: `taken`, the weights' copy and their version. Out: the batch's steps
        (`policy_loop.run`): the policy's rows into the graph's input, one replay each,
        nothing waiting on the host; returns the policy's extras."""
        e = self.engine

        def step(rows: torch.Tensor, t: int) -> dict[str, torch.Tensor]:
            self.u.copy_(rows)
            e.advance()
            # the observations are views of MuJoCo Warp's arrays (or the graph's outputs),
            # which the next step rewrites: the policy keeps copies of its own
            return {k: v.clone() for k, v in e.obs.items()}

        return policy_loop.run(taken, e.config, e.observe_now(), step, e.device)


def driver(engine: Any) -> Any:
    """The engine's driver: the closed loop with a policy, else the open loop."""
    return ClosedLoop(engine) if policy_loop.chosen(engine.config) else OpenLoop(engine)
