"""`impl="warp"`: MuJoCo Warp inside MJX's `jit`/`vmap`/`scan`, through JAX's FFI.

Three things differ from MJX-JAX:

- Buffers of fixed size. Contacts come from one pool shared by every trajectory of the batch
  (`naconmax`), constraint rows from a per-trajectory array (`njmax`). Too small, and Warp drops
  contacts or constraint rows and sets bits in `d._impl.overflow`. Defaults are sized from the
  model: a short MuJoCo C rollout measures the contacts and constraint rows a trajectory uses,
  with a margin of 2x over MuJoCo Warp's own per-world guess; the user can override both. Every
  batch reports the overflow bits per trajectory (`overflow` in the batch, counts in `stats`):
  nothing is dropped silently. Warp's own printing of these events (and of "solver iterations
  limit reached", on every step) is turned off, and the events are counted instead.
- CUDA graphs keyed on buffer addresses. MJX captures Warp's kernels as a CUDA graph (graph mode
  `WARP`) and re-captures it whenever an input buffer moves. In a `lax.scan`, an input set
  straight from the step's control row is a slice of the scanned array, at a new address every
  step: re-capture every step (0.3-0.6M humanoid steps/s instead of 3.9M, measured on an H200).
  `detach` gives every input set from the row, and every recorded output, a buffer of its
  own (`x + 0 * x`: XLA cannot fold `0 * x` for floats), which stays put from step to step.
- Which model fields may differ per trajectory: only those MuJoCo Warp stores with a world axis.
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader import layout
from simloader.backends.mjx.impls import Implementation
from simloader.backends.mjx.runtime import mjx

# mujoco_warp's OverflowType bits: the solver stopping at its iteration limits (which MuJoCo C's
# does silently) is counted; every other bit means a buffer overflowed and something (contacts,
# constraint rows, collision detail) was dropped
_NEFC, _NJMAX_NNZ, _BROADPHASE, _NARROWPHASE, _CCD, _HFIELD = (1 << i for i in range(6))
SOLVER_LIMIT = (1 << 9) | (1 << 10)  # ITERATIONS, LS_ITERATIONS
# calibration of the buffers: trajectories and steps of MuJoCo C, margin over what they used
_CALIBRATION_TRAJECTORIES, _CALIBRATION_STEPS, _MARGIN = 16, 300, 2.0


class WarpImpl(Implementation):
    """MuJoCo Warp.

    Args:
      naconmax: contacts of the whole batch (one pool); None: sized from the model.
      njmax: constraint rows per trajectory; None: sized from the model.
    """

    name = "warp"
    # setconst.py recomputes derived constants with MJX-JAX's kinematics, which Warp models lack
    recomputes_constants = False
    first_batch_hint = ("MuJoCo Warp compiles its kernels for this model on first use on a "
                        "machine (about a minute for a humanoid on an H200, into ~/.cache/warp; "
                        "later processes load them in seconds). `simloader warmup` does it "
                        "ahead of time.")

    def __init__(self, naconmax: int, njmax: int):
        self.naconmax, self.njmax = naconmax, njmax

    def put_model(self, model: mujoco.MjModel, device: jax.Device) -> Any:
        from mujoco.mjx.warp import types as warp_types
        # graph capture on a GPU target even when the model is stacked on the host first
        # (MJX picks the mode from the device it is given)
        mode = warp_types.GraphMode.WARP if device.platform == "gpu" else warp_types.GraphMode.JAX
        mx = mjx.put_model(model, device=device, impl="warp", graph_mode=mode)
        return mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=0)))

    def make_data(self, model: mujoco.MjModel, device: jax.Device) -> Any:
        return mjx.make_data(model, device=device, impl="warp", naconmax=self.naconmax,
                             njmax=self.njmax)

    def detach(self, value: jax.Array) -> jax.Array:
        # Warp's CUDA graph is captured anew whenever a buffer it reads or writes moves. An
        # input set from a slice of the scanned controls, or a kernel output stacked as it is
        # into the scan's output (written in place), is at another address every step
        # (measured: 0.6M humanoid steps/s, and recording xpos halved throughput). A buffer
        # of its own stays put. `x + 0 * x`, not `+ 0 * old`: a bad input of one step does
        # not reach the next (floats only: XLA folds `0 * x` for integers)
        return value + 0 * value if jnp.issubdtype(value.dtype, jnp.floating) else value

    def overflow(self, d: Any) -> jax.Array:
        return d._impl.overflow

    def cannot_randomize(self, field: str) -> Optional[str]:
        from mujoco.mjx.warp import types as warp_types
        key = (field.replace("opt._impl.", "opt__").replace("opt.", "opt__")
               .removeprefix("_impl."))
        if warp_types._BATCH_DIM["Model"].get(key):
            return None
        if field == "opt.impratio":
            return "MuJoCo Warp keeps only a derived 1/sqrt(impratio)"
        return "MuJoCo Warp shares it across all trajectories of a batch"

    def describe(self) -> str:
        return f"warp (naconmax={self.naconmax}, njmax={self.njmax})"


def buffer_sizes(model: mujoco.MjModel, nbatch: int, x0: np.ndarray,
                 naconmax: Optional[int], njmax: Optional[int]) -> tuple[int, int]:
    """(naconmax, njmax) for `nbatch` trajectories: the user's values, else measured.

    Measured: MuJoCo C runs `_CALIBRATION_TRAJECTORIES` trajectories (from initial states `x0`,
    (n, nstate)) under uniform random controls for `_CALIBRATION_STEPS` steps; each buffer gets
    twice the most a trajectory used, and at least MuJoCo Warp's own per-world guess.
    """
    from mujoco.mjx.third_party.mujoco_warp._src import io as warp_io
    if naconmax is not None and njmax is not None:
        return naconmax, njmax
    ncon, nefc = _calibrate(model, x0)
    per_world_contacts = max(warp_io._default_nconmax(model), int(np.ceil(_MARGIN * ncon)))
    rows = max(warp_io._default_njmax(model), int(np.ceil(_MARGIN * nefc)))
    return (naconmax if naconmax is not None else nbatch * per_world_contacts,
            njmax if njmax is not None else rows)


def _calibrate(model: mujoco.MjModel, x0: np.ndarray) -> tuple[int, int]:
    """The most contacts and constraint rows one trajectory of MuJoCo C used."""
    rng = np.random.default_rng(0)
    low, high = np.where(model.actuator_ctrllimited[:, None].astype(bool), model.actuator_ctrlrange,
                         [-1.0, 1.0]).T
    data = mujoco.MjData(model)
    ncon = nefc = 0
    for i in range(min(_CALIBRATION_TRAJECTORIES, len(x0))):
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, x0[i], layout.FULLPHYSICS)
        for _ in range(_CALIBRATION_STEPS):
            data.ctrl[:] = rng.uniform(low, high)
            mujoco.mj_step(model, data)
            ncon, nefc = max(ncon, data.ncon), max(nefc, data.nefc)
    return ncon, nefc


def overflow_message(bits: int, naconmax: int, njmax: int) -> str:
    """What overflowed, and what to raise."""
    advice = []
    if bits & (_BROADPHASE | _NARROWPHASE | _CCD | _HFIELD):
        advice.append(f"contacts exceeded naconmax={naconmax} (the pool of the whole batch): "
                      f"pass a larger naconmax=")
    if bits & (_NEFC | _NJMAX_NNZ):
        advice.append(f"constraint rows exceeded njmax={njmax} per trajectory: pass a larger "
                      f"njmax=")
    return "; ".join(advice)


def solver_notices(bits: jax.Array) -> jax.Array:
    return (bits & SOLVER_LIMIT) != 0


def dropped(bits: jax.Array) -> jax.Array:
    return (bits & ~SOLVER_LIMIT) != 0

