"""MuJoCo Warp's reading of the recorded values (`simloader.observe`'s observations): one frame
of a whole batch from torch views of MuJoCo Warp's data arrays."""

from __future__ import annotations

from typing import Any

import torch

from simloader import observe


def value(o: observe.Observation, fields: dict[str, Any]) -> Any:
    """The value of one frame of `o` for the whole batch, `(nbatch, *o.shape)`, from torch
    tensors `(nbatch, ...)` of the MjData fields `o.fields()` names (MuJoCo Warp's arrays):
    a view of them where the layout allows, else a new tensor."""
    if isinstance(o, observe.State):
        time, *rest = (fields[name] for name in o.fields())
        return torch.cat([time.reshape(-1, 1), *rest], dim=1)
    if isinstance(o, observe.Sensor):
        return fields["sensordata"][:, o.columns[0]:o.columns[1]]
    if isinstance(o, observe.Field):
        held = fields[o.key]
        return held.reshape(held.shape[0], *o.shape)
    raise TypeError(f"MuJoCo Warp computes no {type(o).__name__} ({o.key})")
