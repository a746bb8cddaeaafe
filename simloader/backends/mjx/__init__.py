"""MJX on JAX (`backend="mjx"`): MuJoCo in XLA, on the GPU or the CPU.

  entry.py           what the registry sees: availability, auto's estimate, entry points
  options.py         its options and checks at construction (cache, memory, models, records,
                     randomization)
  runtime.py         importing MJX quietly, JAX's memory and caches, the device, the fork guard
  pool.py            models on the device, batched where they differ
  randomize.py       domain randomization in the jitted function; setconst.py its derived
                     constants
  program.py         the pure batch function (scan over vmapped steps) and its compilation
  stored_program.py  batch functions kept on disk, so that a fresh process does not trace
  closed_loop.py     a torch policy between jitted steps
  drivers.py         the open or the closed loop, chosen once per backend
  backend.py         the backend: each batch dispatched, the hand-off to torch
"""
