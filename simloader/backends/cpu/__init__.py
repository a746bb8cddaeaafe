"""The CPU engine (`backend="cpu"`): MuJoCo's native batched simulation
(`mujoco.batch.Batch`) on a thread pool, bit for bit `mujoco.rollout`.

  entry.py     what the registry sees: availability, auto's estimate, the entry points
  options.py   its checks at construction (cameras, OpenGL, host memory)
  backend.py   each batch: rows, draws, randomization, the hand-off without copies
  drivers.py   the open loop (`Batch.rollout`) and the closed loop (a policy per step)
  render.py    `mujoco.Renderer`s, one per thread, for recorded cameras
"""
