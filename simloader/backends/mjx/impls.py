"""MJX's implementations behind one small interface: `impl="jax"` (MJX in XLA) and `impl="warp"`
(MuJoCo Warp's CUDA kernels, called from JAX through its FFI).

The batch function (`program.py`) is written once against `Implementation`: it resets, sets
the inputs, steps (`mjx.step` dispatches on the model's implementation, as MJX's own
`forward.step` does) and checks every trajectory the same way on both. What differs lives
here: how a model and a trajectory's data are put on the device, what must happen to inputs
before a step, which model fields can differ per trajectory, and the fixed-size buffers Warp
may overflow.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional

import jax
import mujoco
import numpy as np

from simloader.backends.mjx.runtime import WARP_IMPORT_LOG, mjx

IMPLS = ("auto", "jax", "warp")


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

    def refresh(self, d: Any, names: tuple[str, ...]) -> Any:
        """`d` after inputs `names` were set from a per-step control row, ready for
        `mjx.step`: each input as `detach` gives it."""
        return d.replace(**{n: self.detach(getattr(d, n)) for n in names})

    def detach(self, value: jax.Array) -> jax.Array:
        """`value` in the buffer the implementation needs it in: an input set from the scanned
        controls before a step, or a recorded value the scan stacks into the batch's output."""
        return value

    def overflow(self, d: Any) -> Optional[jax.Array]:
        """Per trajectory (of batched `d`), the buffer-overflow bits since the reset, or None
        for an implementation without fixed-size buffers."""
        return None

    def cannot_randomize(self, field: str) -> Optional[str]:
        """Why a model field cannot differ per trajectory on this implementation, or None."""
        return None

    def describe(self) -> str:
        return self.name


@dataclasses.dataclass(frozen=True)
class Choice:
    """The implementation a dataset runs, and why (shown by `describe()` and in `stats`)."""

    impl: str
    reason: str


def choose(asked: str, model: mujoco.MjModel, warp_missing: Optional[str],
           cameras: bool = False, warp_closed_loop: bool = False) -> Choice:
    """Resolves `impl`: "jax" and "warp" as asked; "auto" the faster one available.

    Measured on an H200 (benchmarks/results): MuJoCo Warp is 2.5x MJX-JAX on the humanoid (contacts,
    a constraint solver with many rows), while on a contact-free model JAX's fused XLA step is
    faster (cart-pole 4096: 16.8M vs 13.8M steps/s). So "auto" takes Warp, where it can run, for
    a model with contacts, and JAX otherwise. A closed loop that MuJoCo Warp's own driver can run
    (`warp_closed_loop`, `warp_loop.py`) takes Warp on any model: it replays one CUDA graph per
    step where MJX-JAX dispatches a jitted step (cart-pole 4096 with a torch MLP on an H200:
    7.7M vs 1.9M steps/s).

    Raises:
      TypeError: `impl` is not a string.
      ValueError: `impl` is unknown, or "warp" was asked where it cannot run (`warp_missing`).
    """
    if not isinstance(asked, str):
        raise TypeError(f"impl: expected one of {IMPLS}, got {type(asked).__name__} {asked!r}")
    if asked not in IMPLS:
        raise ValueError(f"impl: expected one of {IMPLS}, got {asked!r}")
    if asked == "warp":
        if warp_missing:
            detail = f" [{WARP_IMPORT_LOG}]" if WARP_IMPORT_LOG else ""
            raise ValueError(f"impl: 'warp' cannot run here: {warp_missing}{detail}; use "
                             f"impl='jax' (or 'auto')")
        return Choice("warp", "asked")
    if asked == "jax":
        return Choice("jax", "asked")
    if warp_missing:
        return Choice("jax", f"auto: {warp_missing}")
    if cameras:
        return Choice("warp", "auto: cameras render only on MuJoCo Warp")
    if warp_closed_loop:
        return Choice("warp", "auto: a policy in the loop runs fastest on MuJoCo Warp's own "
                              "CUDA graph per step")
    if has_contacts(model):
        return Choice("warp", "auto: the model has contacts, where MuJoCo Warp is faster")
    return Choice("jax", "auto: the model has no contacts, where MJX-JAX is faster")


def has_contacts(model: mujoco.MjModel) -> bool:
    """Whether any two geoms may collide (explicit pairs, or contype/conaffinity filtering of
    geoms on different bodies), unless contacts are disabled."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    if model.npair:
        return True
    body = model.geom_bodyid
    contype, conaffinity = model.geom_contype, model.geom_conaffinity
    mask = ((contype[:, None] & conaffinity[None, :]) | (conaffinity[:, None] & contype[None, :]))
    mask = (mask != 0) & (body[:, None] != body[None, :])
    return bool(np.triu(mask, 1).any())
