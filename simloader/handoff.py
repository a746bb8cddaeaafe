"""Handing simulator buffers to torch without copies.

CPU backend: MuJoCo writes into NumPy views of freshly allocated torch tensors (pinned when the
target is a CUDA device, so that the host-to-device copy is asynchronous). MJX backend: JAX
arrays reach torch through DLPack, sharing device memory.
"""

from __future__ import annotations

import collections
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np
import torch
from torch.utils.data._utils.collate import default_collate_fn_map


def host_buffer(shape: tuple[int, ...], dtype: torch.dtype = torch.float64,
                pin: bool = False) -> tuple[torch.Tensor, np.ndarray]:
    """A new torch tensor and a NumPy view of the same memory, for MuJoCo to write into.

    A new tensor per batch keeps a tensor the user holds from ever changing; torch's pinned
    host allocator recycles pinned blocks only once the copies that read them have finished.
    """
    tensor = torch.empty(shape, dtype=dtype, pin_memory=pin)
    return tensor, tensor.numpy()


def torch_dtype(dtype: np.dtype) -> torch.dtype:
    """The torch dtype of a NumPy dtype (float64, int32, bool, ...)."""
    return torch.from_numpy(np.empty(0, dtype)).dtype


def to_target(tensor: torch.Tensor, device: Optional[torch.device],
              dtype: Optional[torch.dtype]) -> torch.Tensor:
    """The tensor on the requested device and dtype: itself when nothing changes (no copy)."""
    if device is not None and tensor.device != device:
        # to the device first, converting there; asynchronous only from host (pinned) memory,
        # since a non-blocking copy to the host could be read before it lands
        tensor = tensor.to(device, non_blocking=tensor.device.type == "cpu")
    return tensor if dtype is None or tensor.dtype == dtype else tensor.to(dtype)


def from_jax(array: Any) -> torch.Tensor:
    """A torch tensor over a JAX array's memory, through DLPack (no copy, same device)."""
    return torch.from_dlpack(array)


class Batch(dict):
    """A delivered batch: a `dict` of tensors (nested for `params`) that torch's default
    collation refuses, because a `DataLoader` with its default `batch_size=1` would stack
    single batches into tensors with an extra leading dimension of 1."""

    def __reduce__(self):
        # pickled (torch.save, pickle.dumps) as an OrderedDict, so that loading needs no
        # simloader: torch.load's weights_only accepts OrderedDict but no other dict type (not
        # even dict's constructor). Not from a DataLoader worker: its queue pickles with
        # multiprocessing's ForkingPickler, whose reducers (simloader.batch registers one)
        # take precedence over this one and keep the type and its named views.
        return collections.OrderedDict, (list(self.items()),)


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
