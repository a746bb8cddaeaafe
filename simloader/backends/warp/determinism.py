"""When MuJoCo Warp gives bit-identical batches for the same seed: a rule on the model alone.

MuJoCo Warp 4.0 allocates contact slots and constraint rows with atomic counters and adds
many floating-point terms with atomic adds, so their order, and the rounding of the sums
over them, can change from run to run. Its `Option.deterministic` does not fix this yet: the
contact and constraint-row orderings (`DeterminismType.CONTACTS`, `CONSTRAINT`) are empty
placeholders in 4.0.0, and `ATOMICS` (run-to-run atomics) made the humanoid 8.8x slower on
an H200 and still left runs apart (issue 39's probe). A sum of two terms added to zero is
the same in either order, so a step is reproducible when no atomic target gets three or more
terms and no slot or row is raced for:

- no contacts (disabled, or no two geoms may collide);
- at most one row can come from each kind of constraint a kernel allocates rows for: limited
  slide and hinge joints, limited ball joints, limited tendons, joints with friction loss,
  tendons with friction loss, and each kind of equality (unless that kind is disabled);
- no tendons (their lengths and Jacobians are atomic sums) and no gravity compensation;
- at most two actuators on any degree of freedom (their forces are atomic adds).

The built-in cart-pole passes (its one limited slider, one actuator); the humanoid does not
(contacts, 21 limited hinges). Measured on the GPU: `benchmarks/experiments/determinism.py`.
"""

from __future__ import annotations

from typing import Optional

import mujoco
import numpy as np

_D = mujoco.mjtDisableBit
_J = mujoco.mjtJoint
_E = mujoco.mjtEq
INSTEAD = ("backend='mjx' gives bit-identical batches with XLA's deterministic ops, and "
           "backend='cpu' always")


def refusal(model: mujoco.MjModel) -> Optional[str]:
    """Why MuJoCo Warp's batches of `model` may differ between runs of the same seed (with
    what to use instead), or None when they cannot."""
    from simloader.backends.auto import has_contacts
    flags = model.opt.disableflags
    if flags & _D.mjDSBL_CONSTRAINT:
        races = []
    else:
        races = ["contacts (their slots and rows are raced for)"] if has_contacts(model) else []
        limited = model.jnt_limited.astype(bool)
        kinds = [("limited slide or hinge joints", _D.mjDSBL_LIMIT,
                  np.count_nonzero(limited & np.isin(model.jnt_type, (int(_J.mjJNT_SLIDE),
                                                                       int(_J.mjJNT_HINGE))))),
                 ("limited ball joints", _D.mjDSBL_LIMIT,
                  np.count_nonzero(limited & (model.jnt_type == int(_J.mjJNT_BALL)))),
                 ("limited tendons", _D.mjDSBL_LIMIT,
                  np.count_nonzero(model.tendon_limited)),
                 ("joints with friction loss", _D.mjDSBL_FRICTIONLOSS,
                  np.count_nonzero(model.dof_frictionloss > 0)),
                 ("tendons with friction loss", _D.mjDSBL_FRICTIONLOSS,
                  np.count_nonzero(model.tendon_frictionloss > 0))]
        kinds += [(f"{name[len('mjEQ_'):].lower()} equality constraints",
                   _D.mjDSBL_EQUALITY, np.count_nonzero(model.eq_type == int(kind)))
                  for name, kind in _E.__members__.items()]
        races += [f"{n} {what} (their constraint rows are raced for)"
                  for what, bit, n in kinds if n > 1 and not flags & bit]
    if model.ntendon:
        races.append(f"{model.ntendon} tendons (lengths and Jacobians summed by atomics)")
    if np.any(model.body_gravcomp > 0) and not flags & _D.mjDSBL_GRAVITY:
        races.append("gravity compensation (summed by atomics)")
    per_dof = _actuators_per_dof(model)
    if per_dof > 2:
        races.append(f"{per_dof} actuators on one degree of freedom (summed by atomics)")
    if not races:
        return None
    return (f"MuJoCo Warp 4.0 orders some of its sums by GPU atomics, so batches of the same "
            f"seed can differ in their last bits, and chaos amplifies that; this model has "
            f"{'; '.join(races)}; {INSTEAD}")


def _actuators_per_dof(model: mujoco.MjModel) -> int:
    """The most actuators acting on one degree of freedom through a joint."""
    counts = np.zeros(model.nv, dtype=int)
    for i in range(model.nu):
        if int(model.actuator_trntype[i]) in (int(mujoco.mjtTrn.mjTRN_JOINT),
                                              int(mujoco.mjtTrn.mjTRN_JOINTINPARENT)):
            counts[model.dof_jntid == model.actuator_trnid[i, 0]] += 1
        else:  # a tendon, site or body transmission reaches many degrees of freedom
            counts += 1
    return int(counts.max(initial=0))
