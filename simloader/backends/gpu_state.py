"""What the GPU engines (MJX, MuJoCo Warp) share about the state they simulate."""

from __future__ import annotations

from mujoco import mjtState as S

# The mjSTATE_FULLPHYSICS components the GPU engines (MJX, Warp) do not simulate: each engine
# refuses a model where one is not empty, so that its FULLPHYSICS row is time, qpos, qvel, act.
# Each: (bit, what it is, the MjModel size that counts it).
GPU_UNSIMULATED = (
    (S.mjSTATE_HISTORY, "actuator and sensor delays", "nhistory"),
    (S.mjSTATE_PLUGIN, "plugins with state", "npluginstate"),
    (S.mjSTATE_PLASTIC, "plasticity", "nplastic"),
)
