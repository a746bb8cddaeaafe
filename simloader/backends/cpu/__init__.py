"""The CPU backend (`backend="rollout"`): MuJoCo's native batched simulation
(`mujoco.batch.Batch`) on a thread pool, bit for bit `mujoco.rollout`.

  options.py   its checks at construction (cameras, OpenGL)
  backend.py   each batch: draws, the open and the closed loop, the hand-off without copies
  render.py    `mujoco.Renderer`s, one per thread, for recorded cameras
"""

from simloader.backends.cpu.backend import RolloutBackend
from simloader.backends.cpu.options import CpuOptions, check_options

__all__ = ["CpuOptions", "RolloutBackend", "check_options"]
