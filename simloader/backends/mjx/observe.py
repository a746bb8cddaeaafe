"""MJX's reading of the recorded values (`simloader.records`): one frame of each from one
trajectory's `mjx.Model`/`mjx.Data`, inside the jitted scan, by each kind's default reading over
`jax.numpy`, and the refusal of what MJX cannot record. MJX's data differ from MuJoCo's in where
a field lives (`field`: public, or under `_impl`) and in the shape of rotation matrices
(`(n, 3, 3)` for MuJoCo's `(n, 9)`, the same values), which the default reading takes;
`READINGS` overrides a kind where more differs (none does today)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Optional

import jax
import mujoco
import numpy as np
from simloader import records
from simloader.backends.mjx.runtime import mjx

# kind -> reading(record, m, d) -> record.shape, where MJX's data differ
READINGS: dict[type, Callable[[records.Record, Any, Any], Any]] = {}


def value(o: records.Record, m: Any, d: Any) -> Any:
    """The value of one frame of `o`, `o.shape`, from one trajectory's `mjx.Model` and
    `mjx.Data` (pure; called inside `vmap` inside the scan body). MJX's dtype (float32
    unless JAX runs with x64; integer and bool fields keep theirs)."""
    reading = records.override(o, READINGS)
    if reading is not None:
        return reading(o, m, d)
    if o.rendered:
        raise TypeError(f"MJX reads no {type(o).__name__} ({o.key}) from its fields")
    return o.value(jax.numpy, {name: field(d, name) for name in o.fields()}, ())


def frame(observations: Sequence[records.Record], model_axes: Any, m: Any,
          d: Any, stage: Optional[int] = None) -> dict[str, Any]:
    """One frame of every observation, `{key: (nbatch, *shape)}`, from the batched `mjx.Data`
    `d` and its `mjx.Model` `m` (batched along `model_axes`); pure, for the scan body, whose
    stacked outputs are then `(nframes, nbatch, *shape)`. With `stage` (an `mjtStage`,
    `record_kinematics="frame"`), read after the forward stages up to it at `d`'s state
    (`at_stage`); the data the loop carries on stay as the step left them."""
    def one(m, d):
        d = at_stage(m, d, stage)
        return {o.key: value(o, m, d) for o in observations if not o.rendered}
    return jax.vmap(one, (model_axes, 0))(m, d)


def at_stage(m: Any, d: Any, stage: Optional[int]) -> Any:
    """One trajectory's data with the forward stages up to `stage` computed at its state:
    `mjx.forward` for mjSTAGE_ACC; for mjSTAGE_VEL the position and velocity stages and their
    sensors, as mj_step1 computes them; `d` itself for None."""
    if stage is None:
        return d
    if stage >= int(mujoco.mjtStage.mjSTAGE_ACC):
        return mjx.forward(m, d)
    d = mjx.sensor_pos(m, mjx.fwd_position(m, d))
    return mjx.sensor_vel(m, mjx.fwd_velocity(m, d))


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


def refusal(o: records.Record, data: Any) -> Optional[str]:
    """Why MJX (whose `make_data` gives `data`) cannot record `o`, or None."""
    for name, shape in o.made_of:
        held = field(data, name)
        if held is None:
            return f"MJX has no field {name}"
        if not isinstance(held, jax.Array):
            return (f"MJX holds {name} as a constant of the compiled "
                    f"model (a size fixed at compilation), not per trajectory")
        if tuple(held.shape) != shape and not (
                name.endswith("mat") and held.size == math.prod(shape)):
            return (f"MJX stores {name} with shape {tuple(held.shape)}, "
                    f"MuJoCo with shape {shape} (another layout, e.g. dense instead of "
                    f"sparse)")
        if np.dtype(held.dtype).kind != o.dtype.kind:
            return f"MJX stores {name} as {held.dtype}, MuJoCo as {o.dtype}"
    return None


def check(observations: Sequence[records.Record], data: Any) -> None:
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
