"""Process-wide concerns of MJX on JAX: importing MJX, JAX's GPU memory and compilation
cache (as `options.py` checked them), the device to simulate on, and the fork guard.

MJX is imported here, once, without its own optional Warp support, which simloader does not use
(its Warp engine drives the public `mujoco-warp` package from torch): where Warp is installed
but not yet imported, MJX would import Warp and its vendored MuJoCo Warp (1-2 s of a JAX
dataset's start) for nothing. MJX then reports Warp as missing in this process:
`mjx.put_model(impl="warp")` in your own code needs `mujoco.mjx` imported before simloader's
first JAX dataset. MJX's "Failed to import warp" prints are captured.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import warnings
from typing import Any, Optional

import jax
import torch
from jax._src import xla_bridge  # private: whether JAX has started (no public query)

from simloader.backends import base

def _import_mjx() -> Any:
    blocked = "warp" not in sys.modules  # an imported Warp costs MJX nothing more
    if blocked:
        sys.modules["warp"] = None  # makes `import warp` raise ImportError
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            from mujoco import mjx
    finally:
        if blocked:
            del sys.modules["warp"]
    return mjx


mjx = _import_mjx()  # re-exported: the backend's modules import it from here

_PREALLOCATE = "XLA_PYTHON_CLIENT_PREALLOCATE"
_FRACTION = "XLA_CLIENT_MEM_FRACTION"
_FRACTION_DEPRECATED = "XLA_PYTHON_CLIENT_MEM_FRACTION"  # jaxlib rejects both being set


# XLA's run-to-run determinism on GPUs (deterministic scatters and reductions): MJX's
# humanoid bit-identical across processes with it, 53 apart in qpos without it (H200,
# benchmarks/results/determinism-2026-11-22.md); read once, when JAX starts its backends
DETERMINISTIC_OPS = "--xla_gpu_deterministic_ops=true"


def determinism_refusal() -> Optional[str]:
    """Why MJX cannot be deterministic in this process, or None: XLA's deterministic GPU ops
    are set, or can still be set (JAX has not started), or JAX runs on the CPU only. A
    question: it changes nothing."""
    if DETERMINISTIC_OPS in os.environ.get("XLA_FLAGS", "").split():
        return None
    if not xla_bridge.backends_are_initialized():
        return None
    if all(d.platform == "cpu" for d in jax.devices()):
        return None  # XLA on the CPU sums in a fixed order
    return (f"JAX started without XLA's deterministic GPU ops; set XLA_FLAGS={DETERMINISTIC_OPS} "
            f"before anything starts JAX (the first SimDataset with deterministic=True, or "
            f"your first jax call, does it), or use backend='cpu'")


def configure_determinism() -> None:
    """Makes XLA's GPU ops deterministic where JAX has not started yet (XLA_FLAGS, for this
    process and its children); where it has, `determinism_refusal` said so at binding."""
    flags = os.environ.get("XLA_FLAGS", "")
    if DETERMINISTIC_OPS not in flags.split() and not xla_bridge.backends_are_initialized():
        os.environ["XLA_FLAGS"] = f"{flags} {DETERMINISTIC_OPS}".strip()


def configure_memory(fraction: Optional[float]) -> None:
    """Sets how JAX takes GPU memory; effective only before JAX starts its backends (said
    where it has).

    Args:
      fraction: as `options.memory_fraction` checks it: None, no preallocation; a number in
        (0, 1], preallocate that fraction.
    """
    if not xla_bridge.backends_are_initialized():  # JAX has no public "started" query
        if fraction is None:
            os.environ.setdefault(_PREALLOCATE, "false")  # a user's explicit choice stands
        else:
            os.environ[_PREALLOCATE] = "true"
            os.environ.pop(_FRACTION_DEPRECATED, None)
            os.environ[_FRACTION] = str(fraction)
        return
    if not any(d.platform == "gpu" for d in jax.devices()):
        return
    # the same test jaxlib applies when it creates the GPU client
    preallocating = os.environ.get(_PREALLOCATE, "true") not in ("false", "False", "0")
    current = os.environ.get(_FRACTION) or os.environ.get(_FRACTION_DEPRECATED)
    if fraction is None and preallocating:
        warnings.warn(
            "simloader: JAX was started before simloader could turn off its GPU memory "
            "preallocation, so JAX may hold 75% of the GPU and leave little to torch. Set "
            f"{_PREALLOCATE}=false before JAX starts (or create the SimDataset first).",
            RuntimeWarning, stacklevel=3)
    elif fraction is not None and current != str(fraction):
        warnings.warn(
            f"simloader: memory_fraction={fraction} has no effect: JAX was already started "
            f"(with {_FRACTION}={current}). Create the SimDataset before anything starts JAX, "
            f"or set {_FRACTION} yourself.", RuntimeWarning, stacklevel=3)


def configure_cache(path: Any) -> None:
    """Points JAX's persistent compilation cache at `path` (`options.compilation_cache`;
    False: left alone)."""
    # JAX reads these at its first compilation in the process; later changes are ignored
    if path is not False:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def refuse_forked_worker() -> None:
    """JAX is multithreaded and deadlocks in a forked child (its parent already ran JAX)."""
    base.refuse_forked_worker("backend='mjx'", "JAX is multithreaded and deadlocks after fork")


def jax_device(target: Optional[torch.device]) -> jax.Device:
    """Where to simulate: JAX GPU k for a `cuda:k` target (no copy at delivery), else JAX's
    GPU of this local rank (torchrun's LOCAL_RANK), else JAX's default device."""
    gpus = [d for d in jax.local_devices() if d.platform == "gpu"]
    if not gpus:
        return jax.local_devices()[0]
    if target is not None and target.type == "cuda":
        index = target.index if target.index is not None else torch.cuda.current_device()
    else:
        index = int(os.environ.get("LOCAL_RANK", "0"))
    # by CUDA ordinal, not by position (JAX may see fewer GPUs than torch)
    for gpu in gpus:
        if gpu.local_hardware_id == index:
            return gpu
    if target is not None and target.type == "cuda":
        raise ValueError(f"device: {target} requested but JAX sees only the GPU(s) "
                         f"{[g.local_hardware_id for g in gpus]}")
    return gpus[index % len(gpus)]


def torch_device(device: jax.Device) -> torch.device:
    """The torch device of JAX device `device` (where DLPack puts its arrays)."""
    if device.platform == "gpu":
        return torch.device("cuda", device.local_hardware_id)
    return torch.device("cpu")


def memory_available(device: jax.Device) -> int:
    """Bytes JAX may still allocate on `device` (a GPU: its limit less what is in use; the
    CPU: the host's available memory)."""
    stats = device.memory_stats() if device.platform == "gpu" else None
    if stats and "bytes_limit" in stats:
        return int(stats["bytes_limit"] - stats.get("bytes_in_use", 0))
    from simloader import memory
    return memory.host_available()
