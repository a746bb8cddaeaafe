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

    def __init__(self, config: Any, device: Any, stats: Any):
        self.stats = stats

    def dispatch(self, program: Program, args: BatchArgs) -> Dispatched:
        """In: the program and its batch function's arguments. Out: the batch dispatched
        (compiled first, once: traced, or loaded from the program store), not waited for."""
        program.compile(args, self.stats)
        dispatched = time.perf_counter()
        outputs, carry = program.run(args)
        return dispatched, outputs, carry, None


class ClosedLoop:
    """A torch policy picks every step's controls; the batch's data is donated to the next."""

    def __init__(self, config: Any, device: Any, stats: Any):
        self.config = config
        self.here = runtime.torch_device(device)  # the policy's rows and observations
        self.snapshot = policy.Snapshot(config.policy, self.here)
        self.previous: Any = None  # the last batch's data (donated to the next)

    def dispatch(self, program: Program, args: BatchArgs) -> Dispatched:
        """In: the program and its batch function's arguments. Out: the batch's steps
        dispatched, the policy between them (one version of its weights per batch), and the
        policy's extras."""
        dispatched = time.perf_counter()
        taken = self.snapshot.take()

        def drive(first: dict[str, torch.Tensor], step: policy_loop.Step) -> dict:
            return policy_loop.run(taken, self.config, first, step, self.here)

        loop = _closed_loop(program, self.config.policy_noise)
        outputs, carry, self.previous, extras = loop.run(args, self.previous, drive)
        return dispatched, outputs, carry, extras


def driver(config: Any, device: Any, stats: Any) -> Any:
    """The driver of `config` on JAX's `device` (compile counts into `stats`): the closed loop
    with a policy, else the open loop."""
    return (ClosedLoop if policy_loop.chosen(config) else OpenLoop)(config, device, stats)
