"""The models trajectories run on, on the device: one model, or a model list or variant pool
stacked into one mjx.Model that is batched only along the fields where the models differ.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader.backends import gpu_state
from simloader.backends.mjx.runtime import mjx
from simloader.config import SimConfig

S = mujoco.mjtState
# The mjSTATE_FULLPHYSICS components MJX simulates. The others must be empty (checked at
# construction), so this spec's layout is FULLPHYSICS's, column for column.
PHYSICS = int(S.mjSTATE_TIME | S.mjSTATE_QPOS | S.mjSTATE_QVEL | S.mjSTATE_ACT)


def put_model(model: mujoco.MjModel, device: jax.Device) -> Any:
    """The model on `device` (not yet batched), in MJX's XLA implementation."""
    return mjx.put_model(model, device=device, impl="jax")


def make_data(model: mujoco.MjModel, device: jax.Device) -> Any:
    """One trajectory's mjx.Data as `make_data` leaves it.

    Raises:
      ValueError: MJX cannot make data for the model (a feature `support.refusal` does not
        name; MJX's own words), not its bare NotImplementedError.
    """
    try:
        return mjx.make_data(model, device=device, impl="jax")
    except NotImplementedError as e:
        raise ValueError(f"model: MJX does not support a feature of this model: {e}; use "
                         f"backend='cpu'") from None


def put_models(config: SimConfig, device: jax.Device) -> tuple[Any, Any]:
    """The model, or the model list or variant pool as one mjx.Model batched only where the
    models differ.

    Returns:
      (model, in_axes): `in_axes` is the model's `vmap` axes, 0 on the fields that differ
      across the list and None elsewhere (None altogether for a single model).

    Raises:
      ValueError: MJX cannot simulate a model, or the models differ in a field MJX compiles in.
    """
    models = config.pool
    names = (["model"] if len(models) == 1 else
             [f"randomize[{i}]" for i in range(len(models))] if config.models is not None else
             [f"randomize: variant[{i}]" for i in range(len(models))])
    # a list is compared and stacked on the host, then moved at once
    host = device if len(models) == 1 else jax.local_devices(backend="cpu")[0]
    puts = []
    for name, model in zip(names, models):
        unsimulated = gpu_state.unsimulated(model)
        if unsimulated:
            raise ValueError(f"{name}: MJX does not support {unsimulated[0]}; use "
                             f"backend='cpu'")
        try:
            puts.append(put_model(model, host))
        except NotImplementedError as e:
            raise ValueError(f"{name}: MJX does not support a feature of this model: {e}; use "
                             f"backend='cpu'") from None
    if len(puts) == 1:
        return puts[0], None
    if models[0].nhfield == 0 and hasattr(puts[0]._impl, "geom_rbound_hfield"):
        # MJX keeps a static copy of geom_rbound, read only to size the patch of a height field
        # a geom collides with: without height fields it would make models differing in a geom
        # size (variants) differ in a compiled-in field for nothing
        puts = [put.replace(_impl=put._impl.replace(
            geom_rbound_hfield=np.zeros_like(put._impl.geom_rbound_hfield))) for put in puts]
    paths, treedef = jax.tree_util.tree_flatten_with_path(puts[0])
    columns = [[leaf for _, leaf in paths]]
    for name, put in zip(names[1:], puts[1:]):
        other, other_def = jax.tree_util.tree_flatten(put)
        if other_def != treedef:
            raise ValueError(
                f"{name}: {static_difference(puts[0], put, 'model')} differs from "
                f"{names[0]}, but MJX compiles it into the simulation; only numeric "
                f"parameters may differ across the models")
        columns.append(other)
    batched, axes = [], []
    for (path, _), column in zip(paths, zip(*columns)):
        same = all(np.array_equal(column[0], leaf) for leaf in column[1:])
        batched.append(column[0] if same else jnp.stack(column))
        axes.append(None if same else 0)
    return jax.device_put(treedef.unflatten(batched), device), treedef.unflatten(axes)


def pooled(config: SimConfig) -> bool:
    """Whether trajectories pick their model from a pool (per-model inputs, one row each)."""
    return config.models is not None or config.variants is not None


def static_difference(a: Any, b: Any, path: str) -> str:
    """The first non-array field (compiled in) where two mjx.Models differ, as a path."""
    if isinstance(a, jax.Array):
        return ""
    if dataclasses.is_dataclass(a):
        parts = [(f".{f.name}", getattr(a, f.name), getattr(b, f.name))
                 for f in dataclasses.fields(a)]
    elif isinstance(a, (tuple, list)) and len(a) == len(b):
        parts = [(f"[{i}]", x, y) for i, (x, y) in enumerate(zip(a, b))]
    else:
        return "" if np.array_equal(a, b) else path
    for name, x, y in parts:
        found = static_difference(x, y, path + name)
        if found:
            return found
    return ""
