"""The Warp engine's two drivers, chosen once per engine: the open loop (a batch's control rows
known before it: drawn on the device, fixed, or the model's defaults; checked and clamped for
the whole batch at once; one graph replay per step) and the closed loop (a torch policy picks
each step's rows; the step graph adds the policy's noise, checks and clamps the rows and keeps
them as they acted).

A driver is given what it reads and calls, never the engine: the configuration, a tensor its buffers
take the dtype and device of, the generators' parameters, and the engine's `advance` (one step;
returns the observations after it), with a policy also `observe_now` (the first observations), the
engine's stream and device. Each driver has two sides, and each method says what it reads (in) and
writes (out), as MuJoCo Warp marks its kernels' arrays. The engine's side is fixed when the engine
is built (its graph reads the buffers the driver allocates): `rows` (the buffer the graph reads step
t's rows of), `row` (inside the graph), `start`, `applied`. The batch's side is called by the
backend inside `WarpSimulation.queued`: `prepare` with the batch's seed and defaults, `run` with the
weights its `policy.Snapshot` took before, outside the lock (a copy of the weights may wait for a
training update).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Optional

import numpy as np
import torch

from simloader import controls
from simloader.backends import policy_loop


class OpenLoop:
    """Rows known before the batch, in one (nbatch, nstep, ncontrol) buffer the graph reads."""

    observes = False  # no policy reads the step's observations

    def __init__(self, config: Any, like: torch.Tensor, params: list,
                 advance: Callable[[], Any]):
        c = config
        self.advance, self.nstep = advance, c.nstep
        f = dict(dtype=like.dtype, device=like.device)
        self.controls = torch.zeros((c.nbatch, c.nstep, c.ncontrol), **f)
        # an explicit control array, on the device once; else the generators and their
        # parameters (the engine's tables), drawn on the device per batch
        self.fixed = (torch.as_tensor(c.control.fixed, **f)
                      if c.control.fixed is not None else None)
        self.plan = c.control if c.control.random else None
        self.params = params

    # -- the engine's side (fixed buffers, read by the graph) --------------------------------

    @property
    def rows(self) -> torch.Tensor:
        """The (nbatch, nstep, ncontrol) rows the step graph reads step t's of (`fused`)."""
        return self.controls

    def row(self, t: torch.Tensor, low: torch.Tensor,
            high: torch.Tensor) -> Optional[torch.Tensor]:
        """In: `t` the (1,) step index. Out: nothing: step `t`'s rows are in `rows`, checked
        and clamped already (`start`); no flags."""
        return None

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
            self.advance()
        return {}


class ClosedLoop:
    """The policy's rows, one step at a time, into the (nbatch, ncontrol) buffer the graph
    reads; the graph keeps them, as they acted, in a (nbatch, nstep, ncontrol) buffer."""

    observes = True  # the policy reads each step's observations, images included

    def __init__(self, config: Any, like: torch.Tensor, noise_params: list,
                 advance: Callable[[], dict[str, torch.Tensor]],
                 observe_now: Callable[[], dict[str, torch.Tensor]],
                 stream: Optional[torch.cuda.Stream], device: torch.device):
        c = config
        self.config, self.noise_params = config, noise_params
        self.advance, self.observe_now = advance, observe_now
        self.stream, self.device = stream, device
        f = dict(dtype=like.dtype, device=like.device)
        self.u = torch.zeros((c.nbatch, c.ncontrol), **f)  # the policy's rows of this step
        self.noise = (torch.zeros((c.nbatch, c.nstep, c.ncontrol), **f)
                      if c.policy_noise is not None else None)
        self.control = torch.empty((c.nbatch, c.nstep, c.ncontrol), **f)  # as they acted

    # -- the engine's side -------------------------------------------------------------------

    @property
    def rows(self) -> torch.Tensor:
        """The (nbatch, nstep, ncontrol) rows as they acted, step t's written by `row`
        before the step graph reads them (`fused`)."""
        return self.control

    def row(self, t: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        """In: `t` the (1,) step index, `low`, `high` the clamp bounds, the policy's rows
        (`u`). Out: step `t`'s rows (plus noise, clamped) into `rows`; returns the (nbatch,)
        flags of rows with a bad control."""
        u = self.u
        if self.noise is not None:
            u = u + self.noise.index_select(1, t)[:, 0]
        u, bad = controls.as_applied(u, low, high, torch)
        self.control.index_copy_(1, t, u[:, None])
        return bad

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
        if self.stream is not None:  # a GPU's
            self.stream.wait_stream(torch.cuda.default_stream(self.device))
        if self.noise is not None:
            self.noise.zero_()
            self.config.policy_noise.sample_torch(seed, self.noise, self.noise_params)

    def run(self, taken: tuple[Any, int]) -> dict[str, torch.Tensor]:
        """In: `taken`, the weights' copy and their version. Out: the batch's steps
        (`policy_loop.run`): the policy's rows into the graph's input, one replay each,
        nothing waiting on the host; returns the policy's extras."""

        def step(rows: torch.Tensor, t: int) -> dict[str, torch.Tensor]:
            self.u.copy_(rows)
            obs = self.advance()
            # the observations are views of MuJoCo Warp's arrays (or the graph's outputs),
            # which the next step rewrites: the policy keeps copies of its own
            return {k: v.clone() for k, v in obs.items()}

        return policy_loop.run(taken, self.config, self.observe_now(), step, self.device)


def driver(config: Any, like: torch.Tensor, tables: Any, advance: Callable[[], Any],
           observe_now: Callable[[], dict[str, torch.Tensor]],
           stream: Optional[torch.cuda.Stream], device: torch.device) -> Any:
    """An engine's driver: the closed loop with a policy, else the open loop.

    Args:
      config: the engine's configuration (a weak proxy: a driver must not keep it alive).
      like: a tensor whose dtype and device the driver's buffers take.
      tables: the engine's `DeviceTables` (the generators' parameters).
      advance, observe_now: the engine's one step and first observations.
      stream, device: the engine's stream (None on the CPU) and torch device.
    """
    if policy_loop.chosen(config):
        return ClosedLoop(config, like, tables.noise_params, advance, observe_now, stream,
                          device)
    return OpenLoop(config, like, tables.control_params, advance)
