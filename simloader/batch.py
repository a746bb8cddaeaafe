"""The delivered batch: a dict of tensors with named views.

`Batch` is a `dict[str, torch.Tensor]` (nested for `params`), which torch's default collation
refuses (`pin_memory` and `default_convert` keep its type: they copy it and update the copy),
plus `view()`, which finds a named part of a key without index arithmetic and
without copying. A batch from a DataLoader worker arrives as a `Batch`, views included (the
worker's queue pickles it with multiprocessing's ForkingPickler, for which a reducer is
registered below); `torch.save`/`pickle` store it as an `OrderedDict`, so that
`torch.load(weights_only=True)` loads it: `Batch(loaded, layout=ds.layout)` gives it its views
back, without copies.

    batch.view("qpos")                     # (nbatch, nframes, nq), out of "state"
    batch.view("qpos", of="initial_state") # (nbatch, nq)
    batch.view("xpos", "hand")             # body hand's rows of a recorded "xpos"
    batch.view("sensordata", "ball")       # sensor ball's columns
    batch.view("ctrl", "elbow")            # actuator elbow's column of "control"
    batch.view("body_mass", "pole")        # body pole's column of batch["params"]["body_mass"]
    batch.view("geom_friction[floor]", "floor[0]")  # a component of geom floor's friction
"""

from __future__ import annotations

import collections
from collections.abc import Mapping, Sequence
from multiprocessing.reduction import ForkingPickler
from typing import Any, Optional

import torch
from torch.utils.data._utils.collate import default_collate_fn_map

from simloader.layout import PARAMS, BatchLayout


class Batch(dict):
    """A batch: `dict[str, torch.Tensor]` with named views.

    torch's default collation refuses it, because a `DataLoader` with its default
    `batch_size=1` would stack single batches into tensors with an extra leading dimension
    of 1.

    Attributes:
      layout: what each column means (`simloader.layout.BatchLayout`), or None for a batch
        made from a plain dict, which has no named views.
    """

    layout: Optional[BatchLayout] = None

    def __init__(self, *args: Any, layout: Optional[BatchLayout] = None, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if layout is not None:
            self.layout = layout

    def __copy__(self) -> "Batch":
        # torch's default_convert and pin_memory copy a mapping and update the copy: keep the
        # type and the layout (pickling gives an OrderedDict, see __reduce__)
        return Batch(self, layout=self.layout)

    def __reduce__(self):
        # pickled (torch.save, pickle.dumps) as an OrderedDict, so that loading needs no
        # simloader: torch.load's weights_only accepts OrderedDict but no other dict type (not
        # even dict's constructor). Not from a DataLoader worker: its queue pickles with
        # multiprocessing's ForkingPickler, whose reducer (registered below) takes precedence
        # over this one and keeps the type and its named views.
        return collections.OrderedDict, (list(self.items()),)

    def view(self, name: str, obj: Optional[str] = None, *, of: Optional[str] = None
             ) -> torch.Tensor:
        """A named part of the batch, sharing its memory (a view, never a copy).

        Args:
          name: a batch key, a state component ("time", "qpos", "qvel", "act", ...) held in
            "state", a control component ("ctrl", "xfrc_applied", ...) held in "control", or
            "sensor:NAME" held in "sensordata", or a key of batch["params"] (a randomized
            parameter, also as "params/KEY").
          obj: an object's part of it, by name: a joint of "qpos"/"qvel", a body of "xpos" or
            "xfrc_applied", an actuator of "ctrl" or "actuator_force", a sensor of
            "sensordata", the object or component column of a randomized parameter ("pole"
            of body_mass, "floor" or "floor[0]" of geom_friction; `ds.describe()` names
            them), ...
          of: the key to take it from (default: `name` itself if recorded, else the key that
            holds it), e.g. "initial_state".

        Returns:
          `(*leading, *part_shape)`: the key's leading axes (nbatch, nframes or nstep; nbatch
          for initial_state) and the part's own shape.

        Raises:
          KeyError: the batch holds no such part (naming what it holds).
        """
        if self.layout is None:
            raise KeyError("this batch has no layout (made from a plain dict): named views need "
                           "the batch a SimDataset delivers")
        part = self.layout.locate(name, obj, of)
        if part.key.startswith(PARAMS) and part.key not in self:  # batch["params"][KEY]
            tensor = self["params"][part.key[len(PARAMS):]]
        else:
            tensor = self[part.key]
        lead = tensor.shape[:tensor.dim() - len(self.layout.keys[part.key])]
        # `view`, not `reshape`: a view or an error, never a silent copy
        flat = tensor.view(*lead, -1) if tensor.dim() > len(lead) else tensor.unsqueeze(-1)
        return flat[..., part.start:part.stop].view(*lead, *part.shape)


def flat(batch: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Every tensor of a batch (or item) by its flat key: `batch["params"][KEY]` as
    `"params/KEY"`, the name the layout, the stores and `nested` use. The one place batch
    keys are flattened."""
    out: dict[str, Any] = {}
    for key, value in batch.items():
        if isinstance(value, Mapping):
            out.update(flat(value, prefix + key + "/"))
        else:
            out[prefix + key] = value
    return out


def nested(flat_keys: Mapping[str, Any]) -> dict[str, Any]:
    """`flat`'s inverse: `"params/KEY"` back into `{"params": {KEY: ...}}`, as a batch holds
    it."""
    out: dict[str, Any] = {}
    for name, value in flat_keys.items():
        if name.startswith(PARAMS):
            out.setdefault(PARAMS[:-1], {})[name[len(PARAMS):]] = value
        else:
            out[name] = value
    return out


def _rebuild(items: list, layout: Optional[BatchLayout]) -> Batch:
    return Batch(items, layout=layout)


def _reduce_across_processes(batch: Batch):
    # a DataLoader worker's queue (and torch.multiprocessing's) pickles with ForkingPickler: its
    # dispatch table, looked up by exact type before `__reduce__`, keeps the type and the
    # layout (so `view` works in the training process); the tensors still go through torch's
    # shared-memory reducers. torch.save and plain pickle do not use this table and keep
    # Batch.__reduce__'s OrderedDict form, which `torch.load(weights_only=True)` accepts (a Batch
    # with its layout, a simloader class, it would refuse).
    return _rebuild, (list(batch.items()), batch.layout)


ForkingPickler.register(Batch, _reduce_across_processes)


def _refuse_collation(batch: Any, *, collate_fn_map: Any = None) -> Any:
    # `batch`: the DataLoader's list of items to stack, as many as its batch_size (fewer only
    # at the end of a finite dataset)
    here = f" (here {len(batch)})" if isinstance(batch, Sequence) else ""
    raise TypeError(f"DataLoader: SimDataset yields whole batches (nbatch trajectories each), "
                    f"so write DataLoader(ds, batch_size=None); with an integer batch_size "
                    f"(the default is 1) the DataLoader stacks that many of them{here}, giving "
                    f"every tensor an extra leading dimension")


# torch's documented extension point of default_collate, also used in DataLoader workers
default_collate_fn_map[Batch] = _refuse_collation
