"""The CPU backend (`backend="cpu"`): MuJoCo's native batched simulation
(`mujoco.batch.Batch`) on a thread pool, bit for bit `mujoco.rollout`.

  options.py   its checks at construction (cameras, OpenGL, host memory)
  backend.py   each batch: rows, draws, randomization, the hand-off without copies
  drivers.py   the open loop (`Batch.rollout`) and the closed loop (a policy per step)
  render.py    `mujoco.Renderer`s, one per thread, for recorded cameras
"""

from simloader.backends.cpu.backend import RolloutBackend
from simloader.backends.cpu.options import CpuOptions, check_options, check_sizes


def create(config, shard, stats) -> RolloutBackend:
    """The engine of one shard (the registry's entry point, as every engine's)."""
    return RolloutBackend(config, shard, stats)


__all__ = ["CpuOptions", "RolloutBackend", "check_options", "check_sizes", "create"]
