"""The Warp engine (`backend="warp"`): MuJoCo Warp (the `mujoco-warp` package)
driven from torch, without JAX.

  entry.py     what the registry sees: availability, auto's estimate, the entry points
  runtime.py   can it run, on which device, importing Warp quietly, the lock on
               Warp's process-wide device and stream
  options.py   its options and checks at construction: models, per-world arrays, buffers
  model_arrays.py  MuJoCo Warp's model arrays by name, which can be per world; the pool's
               per-model arrays
  tables.py    per-model tables and row layouts on the device, gathered per batch
  engine.py    model and data that never move, torch views, the step captured once
  drivers.py   the open and the closed loop: their buffers, each step's control row, a batch
               (given the engine's buffers and callables, not the engine)
  observe.py   each recorded value read from MuJoCo Warp's arrays
  cameras.py   MuJoCo Warp's renderer inside the step (given the engine's model and data)
  determinism.py  which models MuJoCo Warp steps bit-identically
  backend.py   each batch: host draws, per-trajectory state on the device, the hand-off
"""
