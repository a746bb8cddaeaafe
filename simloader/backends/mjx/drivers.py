"""MJX's two drivers, chosen once per backend: the open loop (the whole batch is one call of the
compiled batch function) and the closed loop (a torch policy between jitted steps,
`closed_loop.py`). Each dispatches a batch and says when, what it returns and what it hands over
beside it; neither waits for the device."""

from __future__ import annotations

import time
import weakref
from typing import Any, Optional

import torch

from simloader import handoff, policy
from simloader.backends.mjx import closed_loop, runtime
from simloader.backends.mjx.program import BatchArgs, Program

# each program's closed loop, jitted once and shared by every iterator of its dataset (as the
# program's open-loop batch function is)
_CLOSED_LOOPS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _closed_loop(program: Program, noise: Any) -> closed_loop.ClosedLoop:
    if program not in _CLOSED_LOOPS:
        _CLOSED_LOOPS[program] = closed_loop.ClosedLoop(
            program.pieces, () if noise is None else noise.drivers)
    return _CLOSED_LOOPS[program]

# (dispatched: time.perf_counter() at dispatch, outputs, carry, extras: the policy's tensors
# delivered beside the batch, or None)
Dispatched = tuple[float, dict[str, Any], Any, Optional[dict[str, torch.Tensor]]]


class OpenLoop:
    """Controls drawn inside the batch function (or fixed): one call per batch."""

    def __init__(self, backend: Any):
        self.backend = backend

    def dispatch(self, args: BatchArgs) -> Dispatched:
        b = self.backend
        b.program.compile(args, b.stats)  # once: traced, or loaded from the program store
        dispatched = time.perf_counter()
        outputs, carry = b.program.run(args)
        return dispatched, outputs, carry, None


class ClosedLoop:
    """A torch policy picks every step's controls; the batch's data is donated to the next."""

    def __init__(self, backend: Any):
        self.backend = backend
        self.snapshot = policy.Snapshot(backend.config.policy)
        self.loop = _closed_loop(backend.program, backend.config.policy_noise)
        self.previous: Any = None  # the last batch's data (donated to the next)
        self.caller: Optional[policy.Caller] = None  # this batch's policy calls

    def dispatch(self, args: BatchArgs) -> Dispatched:
        b = self.backend
        c = b.config
        dispatched = time.perf_counter()
        act, version = self.snapshot.take()  # one version of the weights per batch
        self.caller = policy.Caller(act, c.nbatch, c.ncontrol, c.nstep,
                                    c.device or runtime.torch_device(b.device))
        outputs, carry, self.previous = self.loop.run(
            args, self._step, c.nstep, self.previous)
        extras = {**self.caller.extras,
                  policy.VERSION: torch.tensor(version, dtype=torch.int64)}
        return dispatched, outputs, carry, extras

    def _step(self, obs: dict[str, torch.Tensor], t: int) -> torch.Tensor:
        """The policy's control rows for step `t`, from the observations before it (tensors
        on the simulation's device, as the closed loop hands them over), on that device."""
        c = self.backend.config
        tensors = {k: handoff.to_target(v, c.device, c.dtype if v.is_floating_point() else None)
                   for k, v in obs.items()}
        control = self.caller(tensors, t).detach()
        here = runtime.torch_device(self.backend.device)
        if control.device != here:  # a policy on another device than the simulation
            control = control.to(here, non_blocking=True)
        return control


def driver(backend: Any) -> Any:
    """The backend's driver: the closed loop with a policy, else the open loop."""
    return ClosedLoop(backend) if backend.config.policy is not None else OpenLoop(backend)
