"""The simulation backends behind `SimDataset`, by name: "rollout" (CPU) and "mjx" (JAX).

The dataset talks to backends only through this registry: resolve "auto", validate a backend's
options, create one for a shard. Backend modules are imported when first needed, so that a
CPU-only user never imports JAX.
"""

from __future__ import annotations

import glob
import importlib.util
from typing import Any

from simloader import sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig

BACKENDS = ("auto", "rollout", "mjx")


def _mjx_installed() -> bool:
    return importlib.util.find_spec("mujoco.mjx") is not None


def prepare(backend: Any, options: dict[str, Any]) -> None:
    """Process-wide settings that must precede JAX's start, applied before the configuration
    is validated (`backend="auto"` may ask JAX for its devices): the mjx backend's GPU memory."""
    if backend in ("auto", "mjx") and _mjx_installed() and _gpu_visible():
        from simloader.backends.mjx import runtime
        runtime.configure_memory(options.get("memory_fraction"))


def _gpu_visible() -> bool:
    """Whether this machine may have a GPU for JAX, decided without starting JAX: an NVIDIA
    device node, or torch seeing CUDA."""
    if glob.glob("/dev/nvidia[0-9]*"):
        return True
    import torch
    return torch.cuda.is_available()


def resolve(backend: Any) -> str:
    """"auto" is "mjx" when MJX is installed and JAX sees a GPU, else "rollout"; JAX starts
    only where a GPU may be.

    Raises:
      TypeError, ValueError: not one of `BACKENDS`.
    """
    if not isinstance(backend, str):
        raise TypeError(f"backend: expected one of {BACKENDS}, got {type(backend).__name__}")
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if backend != "auto":
        return backend
    if not (_mjx_installed() and _gpu_visible()):
        return "rollout"
    prepare(backend, {})  # JAX starts here: without preallocation unless told otherwise
    try:
        import jax
        return "mjx" if any(d.platform == "gpu" for d in jax.devices()) else "rollout"
    except Exception:  # JAX without a usable platform
        return "rollout"


def check_options(config: SimConfig, asked: str, options: dict[str, Any]) -> Any:
    """Validates backend-specific keyword options at construction (`asked`: the `backend`
    argument before "auto" was resolved); returns them resolved, for `SimConfig.options`."""
    if config.backend == "mjx":
        from simloader.backends import mjx
        return mjx.check_options(config, options)
    if "impl" in options and asked == "auto":
        raise ValueError(
            f"impl: {options['impl']!r} chooses MJX's implementation, but backend='auto' "
            f"resolved to 'rollout' here (no GPU visible to JAX, or mujoco-mjx missing); pass "
            f"backend='mjx' to run MJX anyway")
    if options:
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {sorted(options)} for "
                        f"backend='rollout'")
    return None


def create(config: SimConfig, shard: sharding.Shard, stats: Stats) -> Backend:
    if config.backend == "mjx":
        from simloader.backends.mjx import MjxBackend
        return MjxBackend(config, shard, stats, config.options)
    from simloader.backends.rollout import RolloutBackend
    return RolloutBackend(config, shard, stats)
