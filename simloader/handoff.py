"""Handing simulator buffers to torch without copies: host buffers as NumPy views of
freshly allocated torch tensors (pinned when the target is a CUDA device, so that the
host-to-device copy is asynchronous), and delivered tensors moved to their target device and
dtype. (Each engine hands its own device arrays over: MJX's through DLPack.)"""

from __future__ import annotations

import contextlib
from typing import Any, Optional

import numpy as np
import torch


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


def tensors(batch: dict) -> list[torch.Tensor]:
    """Every tensor of a delivered batch (`params` nested)."""
    out = []
    for value in batch.values():
        out.extend(tensors(value) if isinstance(value, dict) else [value])
    return out


def used_here(batch: dict) -> None:
    """Tells torch's allocator that the consumer's stream uses the delivered tensors (made on
    another stream): their memory is not reused until the consumer's work on them is done."""
    for value in tensors(batch):
        if value.is_cuda:
            value.record_stream(torch.cuda.current_stream(value.device))


@contextlib.contextmanager
def current_device_kept():
    """The calling thread's current CUDA device left as it was by simloader's work inside.

    The consumer's thread builds engines and takes batches, and the simulators' libraries may
    change its current device there: on a 4 x H200 machine, MJX with `sim_device=["cuda:1",
    "cuda:2"]` left the thread on cuda:2 after its first batch (the runtime's device, which
    torch reads), so that a training loop's `torch.randn(..., device="cuda")` afterwards
    would land on a simulation GPU. A thread
    whose torch had not started CUDA counts as on device 0, as torch would start it."""
    before = torch.cuda.current_device() if torch.cuda.is_initialized() else 0
    try:
        yield
    finally:
        if torch.cuda.is_initialized() and torch.cuda.current_device() != before:
            torch.cuda.set_device(before)
