"""What MuJoCo's own recorder (`mujoco.batch`'s rollout, the CPU engine) records each record
from, and each record's value out of that buffer: the record's default reading
(`simloader.records`) over the one field it is made of, a view with no copy.

A record is recorded from its MjData field (`time`, which MjData holds as a float, as the
mjtState spec mjSTATE_TIME), `"state"` from the mjSTATE_FULLPHYSICS spec (in `mj_getState`'s
layout, the plugin state included), and an image into a buffer of its own that the renderer
fills. Records of one source share its buffer (`sensor:NAME` and `sensordata`).
"""

from __future__ import annotations

from typing import Any, Union

import mujoco
import numpy as np

from simloader import layout, records

Shape = tuple[int, ...]
# MjData fields mujoco.batch records as an mjtState spec: time is a float in MjData
_SPECS = {"time": (int(mujoco.mjtState.mjSTATE_TIME), (1,))}
# the kinds recorded whole into a buffer of their own: (source, shape) of the record
_WHOLE = {records.State: lambda o: (layout.FULLPHYSICS, o.shape),
          records.CameraImage: lambda o: (o.key, o.shape)}


def source(o: records.Record) -> tuple[Union[str, int], Shape]:
    """`(source, source_shape)`: the MjData field (or mjtState spec) `mujoco.batch` records
    `o` from, and its trailing shape."""
    whole = records.override(o, _WHOLE)
    if whole is not None:
        return whole(o)
    if len(o.made_of) != 1:
        # mujoco.batch records fields, one buffer each: a kind made of several (other than
        # the state, recorded as its spec) needs its source named in _WHOLE
        raise ValueError(f"record: {o.key!r} is made of {len(o.made_of)} MjData fields "
                         f"{list(o.fields())}; the CPU engine records one field per record "
                         f"(backends/cpu/recorded.py names the exceptions)")
    (name, shape), = o.made_of
    return _SPECS.get(name, (name, shape))


def select(o: records.Record, recorded: Any) -> Any:
    """`o`'s value out of its source's recorded `(..., *source_shape)` buffer (a NumPy array
    or torch tensor): a view, no copy."""
    if records.override(o, _WHOLE) is not None:
        return recorded
    shape = source(o)[1]
    lead = tuple(recorded.shape[:recorded.ndim - len(shape)])
    return o.value(_module(recorded), {o.fields()[0]: recorded}, lead)


def _module(array: Any) -> Any:
    """The array module of a NumPy array or torch tensor."""
    if isinstance(array, np.ndarray):
        return np
    import torch
    return torch
