"""Initial states: fixed arrays, keyframes, or generators that draw fresh states per batch.

States are `mjSTATE_FULLPHYSICS` vectors (`nstate` = `mj_stateSize(model, mjSTATE_FULLPHYSICS)`),
as `mujoco.rollout` takes them. Initial states are small (`nbatch x nstate`), so they are drawn
on the host with NumPy for both backends.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Sequence
from typing import Any, Optional

import mujoco
import numpy as np

from simloader import layout


def keyframe_state(model: mujoco.MjModel, name: Optional[str]) -> np.ndarray:
    """The FULLPHYSICS state of keyframe `name` (`None`: the model defaults, as mj_resetData).

    Raises:
      ValueError: the model has no keyframe of that name.
    """
    data = mujoco.MjData(model)
    if name is not None:
        key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, name)
        if key < 0:
            names = [model.key(i).name for i in range(model.nkey)]
            raise ValueError(f"initial_state: unknown keyframe {name!r}; the model's keyframes "
                             f"are {names}")
        mujoco.mj_resetDataKeyframe(model, data, key)
    state = np.empty(mujoco.mj_stateSize(model, layout.FULLPHYSICS))
    mujoco.mj_getState(model, data, state, layout.FULLPHYSICS)
    return state


def default_states(models: Sequence[mujoco.MjModel], name: Optional[str]) -> np.ndarray:
    """(len(models), nstate): each model's `keyframe_state` (model lists, variants)."""
    return np.stack([keyframe_state(m, name) for m in models])


class InitialStateGenerator(abc.ABC):
    """Base class of initial-state generators: `sample(model, rng, nbatch) -> (nbatch, nstate)`."""

    def check(self, model: mujoco.MjModel) -> None:
        """Validates the generator against the model at construction (raise ValueError)."""

    @abc.abstractmethod
    def sample(self, model: mujoco.MjModel, rng: np.random.Generator, nbatch: int) -> np.ndarray:
        """A float64 (nbatch, nstate) array of FULLPHYSICS states."""


@dataclasses.dataclass(frozen=True)
class Perturbed(InitialStateGenerator):
    """A base state (model defaults or a keyframe) with Gaussian noise on positions and velocities.

    Noise is added to the position of hinge and slide joints and to the translation of free
    joints (quaternions are left unit, untouched), and to every velocity.

    Args:
      qpos_std: standard deviation of the position noise.
      qvel_std: standard deviation of the velocity noise.
      keyframe: name of the base keyframe, or `None` for the model defaults.
    """

    qpos_std: float = 0.1
    qvel_std: float = 0.1
    keyframe: Optional[str] = None

    def check(self, model):
        keyframe_state(model, self.keyframe)
        for name in ("qpos_std", "qvel_std"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ValueError(f"Perturbed.{name}: expected a finite number >= 0, got {v!r}")

    def sample(self, model, rng, nbatch):
        base = keyframe_state(model, self.keyframe)
        out = np.tile(base, (nbatch, 1))
        qpos_cols = 1 + _scalar_qpos(model)
        out[:, qpos_cols] += self.qpos_std * rng.standard_normal((nbatch, len(qpos_cols)))
        qvel = slice(1 + model.nq, 1 + model.nq + model.nv)
        out[:, qvel] += self.qvel_std * rng.standard_normal((nbatch, model.nv))
        return out


def _scalar_qpos(model: mujoco.MjModel) -> np.ndarray:
    """qpos addresses that may take additive noise: hinge, slide and free-joint translations."""
    cols = []
    for j in range(model.njnt):
        adr, kind = int(model.jnt_qposadr[j]), int(model.jnt_type[j])
        if kind == mujoco.mjtJoint.mjJNT_FREE:
            cols.extend(range(adr, adr + 3))
        elif kind in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            cols.append(adr)
    return np.asarray(cols, dtype=np.intp)


class InitialPlan:
    """How each batch's initial states are made, from the dataset's `initial_state` argument."""

    def __init__(self, model: mujoco.MjModel, initial_state: Any, nbatch: int,
                 models: Optional[Sequence[mujoco.MjModel]] = None):
        self.model = model
        self.nstate = mujoco.mj_stateSize(model, layout.FULLPHYSICS)
        self.generator: Optional[InitialStateGenerator] = None
        # the states come from the model (defaults or this keyframe), so each model has its own
        self.from_model = initial_state is None or isinstance(initial_state, str)
        self.keyframe = initial_state if isinstance(initial_state, str) else None
        self._from_rows: Optional[tuple[np.ndarray, int]] = None
        if self.from_model:
            # per model: each trajectory starts from its own model's defaults or keyframe;
            # the nbatch x nstate table is made at its first use, once an engine has accepted
            # the batch's size (a refused nbatch of 10^7 must not build it first)
            self._from_rows = (default_states(models or [model], initial_state), nbatch)
            self._fixed: Optional[np.ndarray] = None
        elif isinstance(initial_state, InitialStateGenerator):
            initial_state.check(model)
            self.generator = initial_state
            self.fixed = None
        else:
            self.fixed = _fixed_initial(initial_state, nbatch, self.nstate)

    @property
    def fixed(self) -> Optional[np.ndarray]:
        """The (nbatch, nstate) initial states every batch starts from, or None (a generator
        draws them)."""
        if self._from_rows is not None and self._fixed is None:
            rows, nbatch = self._from_rows
            self._fixed = np.broadcast_to(rows, (nbatch, self.nstate)).copy()
        return self._fixed

    @fixed.setter
    def fixed(self, value: Optional[np.ndarray]) -> None:
        self._fixed = value

    def sample(self, seed: np.random.SeedSequence, nbatch: int) -> np.ndarray:
        """The (nbatch, nstate) initial states of one batch (fixed ones are returned as is)."""
        if self.generator is None:
            return self.fixed
        out = np.asarray(self.generator.sample(self.model, np.random.default_rng(seed), nbatch),
                         dtype=np.float64)
        if out.shape != (nbatch, self.nstate):
            raise ValueError(f"initial_state generator {type(self.generator).__name__} returned "
                             f"shape {out.shape}, expected ({nbatch}, {self.nstate})")
        return out


def _fixed_initial(value: Any, nbatch: int, nstate: int) -> np.ndarray:
    if not hasattr(value, "__array__") and not isinstance(value, (list, tuple)):
        raise TypeError(
            "initial_state: expected None, an array [nbatch or 1] x nstate, a keyframe name or "
            f"a simloader.initial generator, got {type(value).__name__}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"initial_state: expected a numeric array ({e})") from e
    if arr.ndim == 1:
        arr = arr[None]
    if arr.ndim != 2:
        raise ValueError(f"initial_state: expected 2 dimensions [nbatch or 1] x nstate, got "
                         f"shape {arr.shape}")
    if arr.shape[1] != nstate:
        raise ValueError(f"initial_state: trailing dimension must be nstate={nstate} "
                         f"(mjSTATE_FULLPHYSICS), got {arr.shape[1]}")
    if arr.shape[0] not in (1, nbatch):
        raise ValueError(f"initial_state: leading dimension must be nbatch={nbatch} or 1, got "
                         f"{arr.shape[0]}")
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"initial_state: expected finite values, got {arr[tuple(bad)]} at "
                         f"index {tuple(int(i) for i in bad)}")
    return np.broadcast_to(arr, (nbatch, nstate)).copy()
