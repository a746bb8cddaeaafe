"""The constants MuJoCo derives from masses, inertias, armature and gears, recomputed in JAX.

MuJoCo computes some model fields from others (`mj_setConst`, at compilation and after edits);
MJX reads several of them in its step but has no `set_const` in its JAX implementation. When
the MJX backend randomizes one of `INPUTS` per trajectory, `SetConst` recomputes, per
trajectory and inside the jitted batch function, every derived field MJX's step reads that
depends on them, with MJX's own kinematics and inertia at `qpos0`, following the definitions
of MuJoCo's `engine_setconst.c`:

  body_subtreemass    the body's mass plus its descendants' (MJX: subtree velocities, sensors)
  dof_invweight0      diagonal of inv(M), averaged over the 3 dofs of a ball joint and over the
                      translations and rotations of a free joint (joint limits, friction loss)
  body_invweight0     mean diagonal of J inv(M) J' of the body's com Jacobian, translation and
                      rotation; 0 for bodies welded to the world (contacts, equalities)
  tendon_invweight0   J inv(M) J' of each tendon (tendon limits, friction loss)
  actuator_acc0       |inv(M) moment| of each actuator (muscles)

Bodies MuJoCo compiles as "simple without rotations" (`body_simple == 2`) get 1/mass there, as
in MuJoCo. The other derived fields are left as the model has them: MJX's step does not read
`dof_M0` or `stat`, and the fields `tendon_length0`, `eq_data`, `geom_rbound`, ... derive from
inputs the MJX backend does not randomize (see `mjx_randomize`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader.backends.mjx.runtime import mjx

# mj_setConst inputs handled here: changing them changes only the OUTPUTS (among what MJX reads)
INPUTS = ("body_mass", "body_inertia", "dof_armature", "actuator_gear")
OUTPUTS = ("body_subtreemass", "body_invweight0", "dof_invweight0", "tendon_invweight0",
           "actuator_acc0")
_SIMPLE_TRANSLATION = 2  # body_simple: no rotational dofs, diagonal inertia


class SetConst:
    """`set_const(m, d0) -> {field: value}` for one trajectory's model (vmap it over a batch).

    The index structure (tree, joints, simple and welded bodies) comes from `model` once, on
    the host; only plain arrays are kept, so the function can live in a cached program.
    """

    def __init__(self, model: mujoco.MjModel):
        self.nv, self.nbody = model.nv, model.nbody
        # subtree[i, j] = 1 if body j is body i or one of its descendants (bodies come after
        # their parents, so one backward pass accumulates them)
        subtree = np.eye(model.nbody)
        for i in range(model.nbody - 1, 0, -1):
            subtree[model.body_parentid[i]] += subtree[i]
        self.subtree = subtree
        # moves[b, j] = 1 if dof j moves body b (it belongs to b or to an ancestor of b)
        self.moves = subtree[model.dof_bodyid].T
        self.body_rootid = np.asarray(model.body_rootid)
        # dof_invweight0 = average @ diag(inv(M)): the dof groups MuJoCo averages over
        average = np.eye(model.nv)
        for j in range(model.njnt):
            adr, kind = int(model.jnt_dofadr[j]), int(model.jnt_type[j])
            groups = {mujoco.mjtJoint.mjJNT_FREE: (adr, adr + 3),
                      mujoco.mjtJoint.mjJNT_BALL: (adr,)}.get(kind, ())
            for start in groups:
                average[start:start + 3, start:start + 3] = 1 / 3
        self.average = average
        simple = model.body_simple == _SIMPLE_TRANSLATION
        self.simple_body = simple
        self.simple_dof = simple[model.dof_bodyid]
        self.dof_bodyid = np.asarray(model.dof_bodyid)
        self.world_welded = model.body_weldid == 0

    def __call__(self, m: mjx.Model, d0: mjx.Data) -> dict[str, jax.Array]:
        d = d0.replace(qpos=m.qpos0)
        # MJX's fwd_position, as far as M, tendon Jacobians and actuator moments
        d = mjx.kinematics(m, d)
        d = mjx.com_pos(m, d)
        d = mjx.tendon(m, d)
        d = mjx.crb(m, d)
        d = mjx.tendon_armature(m, d)
        d = mjx.transmission(m, d)
        mass_matrix = mjx.full_m(m, d)
        dtype = mass_matrix.dtype
        minv = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(mass_matrix),
                                          jnp.eye(self.nv, dtype=dtype))
        inverse_mass = 1 / jnp.maximum(mujoco.mjMINVAL, m.body_mass)

        # every body's com Jacobian at once (mjx.jac's, one body at a time, compiles slowly):
        # (nbody, nv, 3) translation and rotation
        offset = d.xipos - d.subtree_com[self.body_rootid]
        moves = jnp.asarray(self.moves, dtype)[..., None]
        jacr = moves * d.cdof[None, :, :3]
        jacp = moves * (d.cdof[None, :, 3:] + jnp.cross(d.cdof[None, :, :3], offset[:, None]))
        body = jnp.stack([jnp.einsum("bvk,vw,bwk->b", jac, minv, jac) / 3
                          for jac in (jacp, jacr)], axis=-1)
        body = jnp.where(self.simple_body[:, None],
                         jnp.stack([inverse_mass, jnp.zeros_like(inverse_mass)], axis=-1), body)
        body = jnp.where(self.world_welded[:, None], 0.0, body)
        dof = jnp.where(self.simple_dof, inverse_mass[self.dof_bodyid],
                        jnp.asarray(self.average, dtype) @ jnp.diagonal(minv))
        # MJX-JAX keeps these under its implementation's private data (the public mjx.Data
        # holds only what every implementation has)
        ten_j, moment = d._impl.ten_J, d._impl.actuator_moment  # (ntendon, nv), (nu, nv)
        return {
            "body_subtreemass": jnp.asarray(self.subtree, dtype) @ m.body_mass,
            "body_invweight0": body,
            "dof_invweight0": dof,
            "tendon_invweight0": jnp.einsum("tv,vw,tw->t", ten_j, minv, ten_j),
            "actuator_acc0": jnp.linalg.norm(moment @ minv, axis=-1),
        }
