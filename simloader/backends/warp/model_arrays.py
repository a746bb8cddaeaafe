"""MuJoCo Warp's model arrays: each by name, which of them MuJoCo Warp can hold per world, and
for a pool (a model list or variants) the values of every model, gathered per batch.

Models are put on Warp's CPU device here (no kernel runs, no GPU is touched): the checks at
construction compare their arrays (`options.py`), and an engine stacks the pool's arrays once.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import mujoco
import torch

from simloader.backends.warp import runtime
from simloader.config import SimConfig

# model fields MuJoCo Warp keeps in another form: field -> (its array, value -> stored value)
CONVERTED = {"opt.impratio": ("opt.impratio_invsqrt", lambda v: v ** -0.5)}


def put(name: str, model: mujoco.MjModel) -> Any:
    """MuJoCo Warp's model of `model` on Warp's CPU device (arrays only, no kernels).

    Raises:
      ValueError: MuJoCo Warp does not support a feature of `model` (named `name`).
    """
    import mujoco_warp as mjw
    wp = runtime.warp()
    try:
        # Warp's current device is the process's: scoped under the engines' lock, or another
        # thread's engine would launch its kernels on the CPU meanwhile
        with runtime.WARP_LOCK, wp.ScopedDevice("cpu"):
            return mjw.put_model(model)
    except NotImplementedError as e:
        raise ValueError(f"{name}: MuJoCo Warp does not support a feature of this model: {e}; "
                         f"use backend='mjx' or backend='cpu'") from None


def arrays(warp_model: Any) -> dict[str, Any]:
    """MuJoCo Warp's model arrays by name (`opt.` for the options'), non-empty ones only."""
    import warp as wp
    out = {}
    for prefix, obj in (("", warp_model), ("opt.", warp_model.opt)):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name, None)
            if isinstance(value, wp.array) and value.size:
                out[prefix + f.name] = value
    return out


def batchable(name: str) -> bool:
    """Whether MuJoCo Warp can hold model array `name` per world (its spec starts with `*`)."""
    # private: MuJoCo Warp's public API does not say which arrays `put_model(batch_sizes=)`
    # can batch; the `*` of each field's array spec in its type definitions is the record
    from mujoco_warp._src import types, warp_util
    cls, field = (types.Option, name[4:]) if name.startswith("opt.") else (types.Model, name)
    spec = {f.name: f.type for f in dataclasses.fields(cls)}.get(field)
    return (spec is not None and warp_util.is_array_spec(spec)
            and getattr(spec, "shape", ())[:1] == ("*",))


def pool_tables(config: SimConfig, pooled: Sequence[str],
                device: torch.device) -> dict[str, torch.Tensor]:
    """For each array of `pooled` (`WarpOptions.pooled`): the values of every model of the
    pool (a model list or variants), (nmodels, ...) on `device`, gathered per batch by model
    index."""
    if not pooled:
        return {}
    tables: dict[str, list] = {f: [] for f in pooled}
    wp = runtime.warp()
    for i, model in enumerate(config.pool):
        held = arrays(put(f"model {i} of the pool", model))
        for f in pooled:
            tables[f].append(wp.to_torch(held[f])[0])
    return {f: torch.stack(rows).to(device) for f, rows in tables.items()}
