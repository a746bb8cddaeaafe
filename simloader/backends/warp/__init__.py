"""The Warp engine (`backend="warp"`): MuJoCo Warp (the `mujoco-warp` package)
driven from torch, without JAX.

  entry.py     what the registry sees: availability, auto's estimate, the entry points
  runtime.py   can it run, on which device, importing Warp quietly, the lock on
               Warp's process-wide device and stream
  options.py   its options and checks at construction: models, per-world arrays, buffers;
               the pool's per-model arrays
  tables.py    per-model tables and row layouts on the device, gathered per batch
  engine.py    model and data that never move, torch views, the step captured once
  drivers.py   the open and the closed loop: their buffers, each step's control row, a batch
  observe.py   each recorded value read from MuJoCo Warp's arrays
  cameras.py   MuJoCo Warp's renderer inside the step
  determinism.py  which models MuJoCo Warp steps bit-identically
  backend.py   each batch: host draws, per-trajectory state on the device, the hand-off
"""
