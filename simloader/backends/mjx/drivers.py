"""MJX's two drivers, chosen once per backend: the open loop (the whole batch is one call of the
compiled batch function) and the closed loop (a torch policy between jitted steps,
`closed_loop.py`). Each dispatches a batch and says when, what it returns and what it hands over
beside it; neither waits for the device."""

from __future__ import annotations

import time
import weakref
from typing import Any, Optional

import torch

from simloader import policy
from simloader.backends import policy_loop
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
        self.snapshot = policy.Snapshot(backend.config.policy,
                                        runtime.torch_device(backend.device))
        self.loop = _closed_loop(backend.program, backend.config.policy_noise)
        self.previous: Any = None  # the last batch's data (donated to the next)

    def dispatch(self, args: BatchArgs) -> Dispatched:
        b = self.backend
        dispatched = time.perf_counter()
        taken = self.snapshot.take()  # one version of the weights per batch
        here = runtime.torch_device(b.device)

        def drive(first: dict[str, torch.Tensor], step: policy_loop.Step) -> dict:
            return policy_loop.run(taken, b.config, first, step, here)

        outputs, carry, self.previous, extras = self.loop.run(args, self.previous, drive)
        return dispatched, outputs, carry, extras


def driver(backend: Any) -> Any:
    """The backend's driver: the closed loop with a policy, else the open loop."""
    return ClosedLoop(backend) if policy_loop.chosen(backend.config) else OpenLoop(backend)
