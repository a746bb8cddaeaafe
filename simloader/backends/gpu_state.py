"""What the GPU engines (MJX, MuJoCo Warp) share about the state they simulate."""

from __future__ import annotations

import mujoco
from mujoco import mjtState as S

# The mjSTATE_FULLPHYSICS components the GPU engines (MJX, Warp) do not simulate: each engine
# refuses a model where one is not empty, so that its FULLPHYSICS row is time, qpos, qvel, act.
# Each: (bit, what it is, the MjModel size that counts it).
GPU_UNSIMULATED = (
    (S.mjSTATE_HISTORY, "actuator and sensor delays", "nhistory"),
    (S.mjSTATE_PLUGIN, "plugins with state", "npluginstate"),
    (S.mjSTATE_PLASTIC, "plasticity", "nplastic"),
)


def unsimulated(model: mujoco.MjModel) -> list[str]:
    """What of `model`'s state the GPU engines do not simulate, each as "what (size=n)"
    (`GPU_UNSIMULATED`; empty for a model they can simulate)."""
    return [f"{what} ({size}={mujoco.mj_stateSize(model, int(bit))})"
            for bit, what, size in GPU_UNSIMULATED if mujoco.mj_stateSize(model, int(bit))]
