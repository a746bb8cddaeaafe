"""The simulation backends behind `SimDataset`: "rollout" (CPU) and "mjx" (JAX)."""

from __future__ import annotations

import importlib.util
from typing import Any

from simloader import sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig


def prepare(backend: Any, options: dict[str, Any]) -> None:
    """Process-wide settings that must precede JAX's start, applied before the configuration
    is validated (`backend="auto"` asks JAX for its devices): the mjx backend's GPU memory."""
    if backend in ("auto", "mjx") and importlib.util.find_spec("mujoco.mjx") is not None:
        from simloader.backends import mjx
        mjx.configure_memory(options.get("memory_fraction"))


def check_options(config: SimConfig, options: dict[str, Any]) -> dict[str, Any]:
    """Validates backend-specific keyword options at construction."""
    if config.backend == "mjx":
        from simloader.backends import mjx
        return mjx.check_options(config, options)
    if options:
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {sorted(options)} for "
                        f"backend='rollout'")
    return {}


def create(config: SimConfig, shard: sharding.Shard, stats: Stats,
           options: dict[str, Any]) -> Backend:
    if config.backend == "mjx":
        from simloader.backends import mjx
        return mjx.MjxBackend(config, shard, stats, **options)
    from simloader.backends.rollout import RolloutBackend
    return RolloutBackend(config, shard, stats)
