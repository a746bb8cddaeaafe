"""MuJoCo Warp's reading of the recorded values (`simloader.records`): one frame of a whole
batch from torch views of MuJoCo Warp's data arrays, by each kind's default reading over
torch; `READINGS` overrides a kind where Warp's data differ from MuJoCo's (none does today:
Warp holds every field a record reads under MuJoCo's name, values in MuJoCo's order)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from simloader import records

# kind -> reading(record, fields) -> (nbatch, *record.shape), where Warp's data differ
READINGS: dict[type, Callable[[records.Record, dict[str, Any]], Any]] = {}


def value(o: records.Record, fields: dict[str, Any]) -> Any:
    """The value of one frame of `o` for the whole batch, `(nbatch, *o.shape)`, from torch
    tensors `(nbatch, ...)` of the MjData fields `o.fields()` names (MuJoCo Warp's arrays):
    a view of them where the layout allows, else a new tensor."""
    reading = records.override(o, READINGS)
    if reading is not None:
        return reading(o, fields)
    if o.rendered:
        raise TypeError(f"MuJoCo Warp reads no {type(o).__name__} ({o.key}) from its fields")
    return o.value(torch, fields, tuple(fields[o.fields()[0]].shape[:1]))
