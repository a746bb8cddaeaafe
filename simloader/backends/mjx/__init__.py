"""The MJX backend (`backend="mjx"`): MuJoCo in JAX on the GPU, with MJX's implementations
`impl="jax"` and `impl="warp"` (MuJoCo Warp).

  runtime.py    importing MJX quietly, JAX's memory and caches, the device, the fork guard
  impls.py      the implementation interface, MJX-JAX, and how `impl="auto"` chooses
  warp_impl.py  MuJoCo Warp: buffer sizes, overflow, inputs that keep CUDA graphs valid
  pool.py       models on the device, batched where they differ
  randomize.py  domain randomization in the jitted function; setconst.py its derived constants
  program.py    the pure batch function (scan over vmapped steps) and its compilation
  backend.py    options, the backend, the hand-off to torch
"""

from simloader.backends.mjx.backend import MjxBackend, MjxOptions, check_options
from simloader.backends.mjx.runtime import configure_memory

__all__ = ["MjxBackend", "MjxOptions", "check_options", "configure_memory"]
