"""The closed loop, written once for every engine: a torch policy picks each step's control rows
from the observations of the state before it.

An engine's closed-loop driver supplies what only it can do, as one function, `step(rows, t)`:
apply the policy's rows of step `t` as MuJoCo would (the policy's noise added, the bad-control
rule, MuJoCo's clamp, all in the engine's own arrays), advance every trajectory one step,
record the frame when due, and return the next observations. This loop does the rest, the
same on every engine: the observations handed over as `record` and `dtype=`/`device=` say, the
policy called and checked (`policy.Caller`), its rows brought to the simulation's device, its
extras and the weights' version delivered beside the batch.

A new driver of this kind (one that picks each step's rows: a planner, a replay with
corrections) is a function beside `run` over the same `step`; the engines need nothing new.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from simloader import handoff, policy

# step(rows, t) -> the observations after step t ({key: (nbatch, ...)} tensors of their own on
# the simulation's device): the engine's part of one step of the closed loop
Step = Callable[[torch.Tensor, int], dict[str, torch.Tensor]]


def chosen(config: Any) -> bool:
    """Whether a batch of `config` runs closed loop (a driver here picks each step's rows)
    rather than each engine's open loop: what every engine's `drivers.driver` asks."""
    return config.policy is not None


def run(taken: tuple[Callable, int], config: Any, first: dict[str, torch.Tensor], step: Step,
        device: torch.device) -> dict[str, torch.Tensor]:
    """One batch of the closed loop: `config.nstep` policy calls, each followed by `step`.

    Args:
      taken: the policy's weights for this batch and their version (`policy.Snapshot.take`).
      config: the dataset's `SimConfig`.
      first: the observations of the initial state (derived fields by a forward pass).
      step: the engine's step (`Step`).
      device: the simulation's torch device (where `step` takes the rows).

    Returns:
      the extras delivered beside the batch: the policy's ("policy/KEY", (nbatch, nstep, ...))
      and the version of its weights.
    """
    c = config
    act, version = taken
    # rows on a named `device=` are checked there; any rows are then brought to the simulation
    caller = policy.Caller(act, c.nbatch, c.ncontrol, c.nstep, c.device)
    # `dtype=` applies to floating values, never to images (depth stays float32 metres)
    floating = {o.key for o in c.observations if o.floating}
    obs = first
    for t in range(c.nstep):
        tensors = {k: handoff.to_target(v, c.device, c.dtype if k in floating else None)
                   for k, v in obs.items()}
        rows = caller(tensors, t).detach()
        if rows.device != device:  # a policy on another device than the simulation
            # (to the host: a blocking copy, since the engine reads the rows at once)
            rows = rows.to(device, non_blocking=device.type == "cuda")
        obs = step(rows, t)
    return {**caller.extras, policy.VERSION: torch.tensor(version, dtype=torch.int64)}
