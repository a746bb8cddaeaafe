"""The simulation backends behind `SimDataset`: "rollout" (CPU) and "mjx" (JAX)."""

from __future__ import annotations

from typing import Any

from simloader import sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig


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
