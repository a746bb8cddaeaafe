"""How far an engine's physics is from MuJoCo C's for a model (`simloader check MODEL`):
trajectories stepped by the engine, then stepped again by MuJoCo C (`mujoco.rollout`, what the
CPU engine runs bit for bit) from the engine's own states with the controls the engine
applied, so that a user sees a drift (MJX's or MuJoCo Warp's float32 arithmetic, a feature
approximated on the GPU) before training on it.

Two numbers per quantity, both the largest absolute difference over every trajectory:

- **one step**: each frame of the engine against one MuJoCo C step from the engine's frame
  before it (the same state, controls and warmstart-free start): the error of a single step,
  which does not grow with the horizon;
- **over the batch**: the engine's last frame against MuJoCo C's trajectory from the same
  initial state with the same controls, which chaos (contacts, a falling humanoid) makes grow
  with any difference at all, and which is shown for scale.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import mujoco
import numpy as np
from mujoco import rollout

from simloader import controls as controls_
from simloader.layout import FULLPHYSICS

S = mujoco.mjtState


@dataclasses.dataclass(frozen=True)
class Accuracy:
    """Largest absolute differences from MuJoCo C (`check`), per quantity."""

    backend: str
    nbatch: int
    nstep: int
    one_step: dict[str, float]
    over_batch: dict[str, float]

    def __str__(self) -> str:
        lines = [f"backend={self.backend!r} against MuJoCo C (mujoco.rollout), {self.nbatch} "
                 f"trajectories x {self.nstep} steps, largest absolute differences:",
                 f"  {'':6} {'one step':>12} {'over the batch':>16}"]
        for key in self.one_step:
            lines.append(f"  {key:6} {self.one_step[key]:12.3g} {self.over_batch[key]:16.3g}")
        lines.append("  one step: each engine frame against one MuJoCo C step from the "
                     "engine's frame before it; over the batch: the last frames, from the "
                     "same start (grows with chaos)")
        return "\n".join(lines)


def check(model: Any, backend: str, *, nbatch: int = 16, nstep: int = 50, seed: int = 0,
          control: Any = None, **options: Any) -> Accuracy:
    """Steps `nbatch` trajectories of `model` for `nstep` steps on `backend` (uniform random
    controls unless `control=` says otherwise; `options` go to `SimDataset`), and compares
    them with MuJoCo C's steps from the same states and controls.

    Raises:
      ValueError: as `SimDataset` for the model and engine (an engine that refuses the model
        says so by name).
    """
    from simloader.dataset import SimDataset
    ds = SimDataset(model, backend=backend, nbatch=nbatch, nstep=nstep, seed=seed,
                    num_batches=1, record=("state",),
                    control=controls_.Uniform() if control is None else control, **options)
    batch = next(iter(ds))
    m = ds.model
    state = batch["state"].cpu().numpy().astype(np.float64)
    start = batch["initial_state"].cpu().numpy().astype(np.float64)
    applied = batch["control"].cpu().numpy().astype(np.float64)
    spec = ds.config.control_spec
    datas = [mujoco.MjData(m) for _ in range(2)]
    # one step from each of the engine's frames (the initial state, then frames 0..T-2)
    before = np.concatenate([start[:, None], state[:, :-1]], axis=1).reshape(-1, state.shape[-1])
    stepped, _ = rollout.rollout(m, datas, before, applied.reshape(-1, 1, applied.shape[-1]),
                                 control_spec=spec, nstep=1)
    one = stepped[:, 0].reshape(state.shape)
    whole, _ = rollout.rollout(m, datas, start, applied, control_spec=spec)
    parts = _parts(m)
    return Accuracy(backend=ds.config.backend, nbatch=nbatch, nstep=nstep,
                    one_step={k: _largest(one[..., c] - state[..., c]) for k, c in parts.items()},
                    over_batch={k: _largest(whole[:, -1, c] - state[:, -1, c])
                                for k, c in parts.items()})


def _parts(model: mujoco.MjModel) -> dict[str, slice]:
    """The mjSTATE_FULLPHYSICS columns of positions and velocities."""
    nq, nv = model.nq, model.nv
    assert mujoco.mj_stateSize(model, FULLPHYSICS) >= 1 + nq + nv
    return {"qpos": slice(1, 1 + nq), "qvel": slice(1 + nq, 1 + nq + nv)}


def _largest(difference: np.ndarray) -> float:
    return float(np.nanmax(np.abs(difference))) if difference.size else 0.0
