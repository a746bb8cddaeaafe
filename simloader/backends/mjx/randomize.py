"""Domain randomization on the MJX backend: a randomization spec bound to a batched mjx.Model.

Parameter values are drawn inside the jitted batch function (`RandomizationPlan.sample_jax`,
keyed by the batch's RANDOMIZE seed) and written into the randomized fields, which alone carry
a batch axis (`in_axes` 0; every other field stays shared, `in_axes` None). When a field is an
input of `mj_setConst` the constants MJX reads are recomputed per trajectory in the same
function (`setconst.py`). Values change, shapes do not: nothing recompiles.

MJX compiles some facts about a model into the simulation when the model is put on the device
(which dofs have friction loss, whether fluid forces exist, geometry bounds, ...), and has no
`mj_setConst`; so only `FIELDS` can be randomized here, and the rest is refused at construction
with that list (`backend="cpu"` randomizes any floating-point field).
"""

from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader import randomize as dr
from simloader.backends.mjx.runtime import mjx
from simloader.backends.mjx import setconst as mjx_setconst

# Fields MJX reads during a step and MuJoCo derives nothing from (mj_setConst), so a new value
# is all it takes; grouped for the README.
_CONTACT = ("geom_friction", "geom_solref", "geom_solimp", "geom_solmix", "pair_friction",
            "pair_solref", "pair_solreffriction", "pair_solimp")
_CONSTRAINTS = ("jnt_solref", "jnt_solimp", "jnt_range", "jnt_margin", "dof_solref",
                "dof_solimp", "eq_solref", "eq_solimp", "tendon_solref_lim",
                "tendon_solimp_lim", "tendon_solref_fri", "tendon_solimp_fri", "tendon_range",
                "tendon_margin")
_PASSIVE = ("dof_damping", "dof_dampingpoly", "dof_frictionloss", "jnt_stiffness",
            "jnt_stiffnesspoly", "tendon_frictionloss",
            # mj_setConst reads these only for sleeping, which MJX does not do
            "tendon_stiffness", "tendon_stiffnesspoly", "tendon_damping", "tendon_dampingpoly")
_ACTUATION = ("actuator_gainprm", "actuator_biasprm", "actuator_dynprm", "actuator_ctrlrange",
              "actuator_forcerange", "actuator_actrange", "actuator_lengthrange",
              "jnt_actfrcrange", "tendon_actfrcrange")
_OPTIONS = ("opt.gravity", "opt.timestep", "opt.impratio", "opt.tolerance", "opt.ls_tolerance",
            "opt.magnetic", "opt.density", "opt.viscosity", "opt.wind")
# what cameras see: no effect on the physics (MJX does not render); their values are
# delivered in `params` as on the other engines
_LOOKS = ("geom_rgba", "mat_rgba", "mat_emission", "mat_specular", "mat_shininess",
          "light_ambient", "light_diffuse", "light_specular", "light_attenuation", "cam_fovy")
FIELDS = (_CONTACT + _CONSTRAINTS + _PASSIVE + _ACTUATION + mjx_setconst.INPUTS + _OPTIONS
          + _LOOKS)

# MJX keeps constraint rows only for the dofs and tendons whose friction loss is > 0 in the model
_FRICTIONLOSS = ("dof_frictionloss", "tendon_frictionloss")
# MJX turns fluid forces on only if the model has density, viscosity or wind
_FLUID = ("opt.density", "opt.viscosity", "opt.wind")
# what mj_setConst computes (refused: randomize its inputs)
_DERIVED = mjx_setconst.OUTPUTS + (
    "dof_M0", "tendon_length0", "tendon_lengthspring", "actuator_length0", "geom_rbound",
    "geom_aabb", "cam_pos0", "cam_poscom0", "cam_mat0", "light_pos0", "light_poscom0",
    "light_dir0")


def check(model: mujoco.MjModel, mx: mjx.Model, plan: dr.RandomizationPlan) -> None:
    """Refuses, by name, the parameters MJX cannot randomize faithfully.

    Raises:
      ValueError: a field outside `FIELDS`, a friction loss the model has at zero, or a fluid
        option of a model without fluid forces; the message lists what can be randomized.
    """
    for r in plan.resolved:
        field, key = r.field, r.param.key
        if field not in FIELDS:
            raise ValueError(
                f"randomize: {key}: backend='mjx' cannot randomize {field} ({_why(field, mx)}); "
                f"it can randomize {', '.join(FIELDS)} (backend='cpu' randomizes any "
                f"floating-point field)")
        if field in _FRICTIONLOSS and np.any(r.base <= 0):
            raise ValueError(
                f"randomize: {key}: backend='mjx' randomizes {field} only where the model's "
                f"value is > 0 (MJX decides when the model is loaded which constraints have "
                f"friction loss); give the model a positive {field} there, or use "
                f"backend='cpu'")
        if field in _FLUID and not (model.opt.density > 0 or model.opt.viscosity > 0
                                    or np.any(model.opt.wind)):
            raise ValueError(
                f"randomize: {key}: backend='mjx' randomizes {field} only in a model with fluid "
                f"forces (MJX turns them off when the model's density, viscosity and wind are "
                f"all 0); give the model a nonzero value, or use backend='cpu'")


def _why(field: str, mx: mjx.Model) -> str:
    if field in _DERIVED:
        return "MuJoCo derives it from other fields"
    value = getattr(mx.opt, field[4:], None) if field.startswith("opt.") else getattr(mx, field,
                                                                                    None)
    if value is not None and not isinstance(value, jax.Array):
        return "MJX compiles it into the simulation"
    if field in mujoco.MjModel._setconst_inputs:
        return "MuJoCo derives constants from it that the MJX backend does not recompute"
    return "not supported by the MJX backend"


def _get(tree: Any, field: str) -> Any:
    return getattr(tree.opt, field[4:]) if field.startswith("opt.") else getattr(tree, field)


def _replace(tree: Any, field: str, value: Any) -> Any:
    """`tree` (an mjx.Model, or its in_axes) with `field` (`opt.*` too) replaced."""
    if field.startswith("opt."):
        return tree.replace(opt=tree.opt.replace(**{field[4:]: value}))
    return tree.replace(**{field: value})


class Randomizer:
    """Writes a batch's drawn values into the model (in the jitted function).

    Args:
      model: the MjModel the plan was resolved against (host).
      plan: the randomization spec.
      axes: the `in_axes` of the model before randomization (None: all shared).
      mx: the mjx.Model (for its structure).
    """

    def __init__(self, model: mujoco.MjModel, plan: dr.RandomizationPlan, axes: Any,
                 mx: mjx.Model):
        self.plan = plan
        self.base_axes = jax.tree.map(lambda _: None, mx) if axes is None else axes
        fields = {r.field for r in plan.resolved}
        self.setconst = (mjx_setconst.SetConst(model)
                         if fields & set(mjx_setconst.INPUTS) else None)
        batched = fields | (set(mjx_setconst.OUTPUTS) if self.setconst else set())
        self.axes = self.base_axes
        for field in sorted(batched):
            self.axes = _replace(self.axes, field, 0)

    def __call__(self, m: mjx.Model, d0: mjx.Data, values: dict[str, jax.Array],
                 nbatch: int) -> mjx.Model:
        """The model with `values` ({key: (nbatch, nvalues)}) in place, batched along
        `self.axes`, and its derived constants recomputed."""
        axes = self.base_axes
        for r in self.plan.resolved:
            current = _get(m, r.field)
            if _get(axes, r.field) is None:
                current = jnp.broadcast_to(current, (nbatch, *current.shape))
            flat = current.reshape(nbatch, -1).at[:, r.elements].set(
                values[r.param.key].astype(current.dtype))
            m = _replace(m, r.field, flat.reshape(current.shape))
            axes = _replace(axes, r.field, 0)
        if self.setconst is not None:
            m = m.replace(**jax.vmap(self.setconst, (axes, None))(m, d0))
        return m


def gather(m: mjx.Model, axes: Optional[Any], index: jax.Array) -> mjx.Model:
    """Per trajectory, the model `index` of a pool batched along `axes` (model-list axes)."""
    if axes is None:
        return m
    return jax.tree.map(lambda axis, x: x if axis is None else x[index], axes, m,
                        is_leaf=lambda x: x is None)
