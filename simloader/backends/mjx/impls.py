"""MJX's implementation behind one small interface, `Implementation` (`impl="jax"`: MJX in
XLA): how a model and a trajectory's data are put on the device, which model fields can differ
per trajectory. The batch function (`program.py`) is written against it. MuJoCo Warp is an
engine of its own (`simloader/backends/warp/`), driven from torch, not through MJX.
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import mujoco

from simloader.backends.mjx.runtime import mjx

class Implementation:
    """`impl="jax"`: MJX's XLA implementation. Runs anywhere JAX runs."""

    name = "jax"
    # whether a randomized input of mj_setConst gets its derived constants recomputed in the
    # batch function (setconst.py), i.e. whether those inputs can be randomized
    recomputes_constants = True

    def put_model(self, model: mujoco.MjModel, device: jax.Device) -> Any:
        """The model on `device` (not yet batched)."""
        return mjx.put_model(model, device=device, impl=self.name)

    def make_data(self, model: mujoco.MjModel, device: jax.Device) -> Any:
        """One trajectory's mjx.Data as `make_data` leaves it."""
        return mjx.make_data(model, device=device, impl=self.name)

    # what a user is told while the first batch runs, if it may take long (None: nothing)
    first_batch_hint: Optional[str] = None

    def cannot_randomize(self, field: str) -> Optional[str]:
        """Why a model field cannot differ per trajectory on this implementation, or None."""
        return None

    def describe(self) -> str:
        return self.name
