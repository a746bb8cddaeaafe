"""MJX's reading of the recorded values (`simloader.observe`'s observations): one frame of each
from one trajectory's `mjx.Model`/`mjx.Data`, inside the jitted scan, and the refusal of what
MJX cannot record."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Optional

import jax
import mujoco
import numpy as np
from simloader import observe
from simloader.backends.mjx.runtime import mjx

# the components of mjSTATE_FULLPHYSICS that MJX simulates (the others must be empty there)
_PHYSICS = int(mujoco.mjtState.mjSTATE_TIME | mujoco.mjtState.mjSTATE_QPOS
               | mujoco.mjtState.mjSTATE_QVEL | mujoco.mjtState.mjSTATE_ACT)


def value(o: observe.Observation, m: Any, d: Any) -> Any:
    """The value of one frame of `o`, `o.shape`, from one trajectory's `mjx.Model` and
    `mjx.Data` (pure; called inside `vmap` inside the scan body). MJX's dtype (float32
    unless JAX runs with x64; integer and bool fields keep theirs)."""
    if isinstance(o, observe.State):
        return mjx.get_state(m, d, _PHYSICS)
    if isinstance(o, observe.Sensor):
        return d.sensordata[o.columns[0]:o.columns[1]]
    if isinstance(o, observe.Field):
        # rotation matrices are (n, 3, 3) in MJX, (n, 9) in MuJoCo: the same values, row-major
        return field(d, o.key).reshape(o.shape)
    raise TypeError(f"MJX computes no {type(o).__name__} ({o.key})")


def frame(observations: Sequence[observe.Observation], model_axes: Any, m: Any,
          d: Any) -> dict[str, Any]:
    """One frame of every observation, `{key: (nbatch, *shape)}`, from the batched `mjx.Data`
    `d` and its `mjx.Model` `m` (batched along `model_axes`); pure, for the scan body, whose
    stacked outputs are then `(nframes, nbatch, *shape)`."""
    return jax.vmap(lambda m, d: {o.key: value(o, m, d) for o in observations
                                  if not o.rendered}, (model_axes, 0))(m, d)


def field(d: Any, name: str) -> Any:
    """MjData field `name` of an mjx.Data: a public field, or one the implementation keeps
    under `d._impl` (cfrc_ext, cacc, subtree_linvel, ... differ per implementation); None if
    MJX has no such field."""
    if name in getattr(type(d), "__dataclass_fields__", {}) and name != "_impl":
        return getattr(d, name)
    impl = getattr(d, "_impl", None)
    if impl is not None and name in getattr(type(impl), "__dataclass_fields__", {}):
        return getattr(impl, name)
    return None


def refusal(o: observe.Observation, data: Any) -> Optional[str]:
    """Why MJX (whose `make_data` gives `data`) cannot record `o`, or None."""
    if not isinstance(o, observe.Field):
        return None
    held = field(data, o.key)
    if held is None:
        return f"MJX has no field {o.key}"
    if not isinstance(held, jax.Array):
        return (f"MJX holds {o.key} as a constant of the compiled "
                f"model (a size fixed at compilation), not per trajectory")
    if tuple(held.shape) != o.shape and not (
            o.key.endswith("mat") and held.size == math.prod(o.shape)):
        return (f"MJX stores {o.key} with shape {tuple(held.shape)}, "
                f"MuJoCo with shape {o.shape} (another layout, e.g. dense instead of "
                f"sparse)")
    if np.dtype(held.dtype).kind != o.dtype.kind:
        return f"MJX stores {o.key} as {held.dtype}, MuJoCo as {o.dtype}"
    return None


def check(observations: Sequence[observe.Observation], data: Any) -> None:
    """Refuses, by name and with the reason, what MJX cannot record.

    Field names are checked against `data`, one trajectory's `mjx.Data` (public fields, and
    those MJX's XLA implementation keeps under `_impl`, `DataJAX`), their shapes and dtype
    kinds against MuJoCo's. Run on the host at construction.

    Raises:
      ValueError: naming every refused observation and why.
    """
    refused = [f"{o.key}: {why}" for o in observations
               if (why := refusal(o, data)) is not None]
    if refused:
        raise ValueError("record: backend='mjx' cannot record " + "; ".join(refused)
                         + "; use backend='cpu' for these")
