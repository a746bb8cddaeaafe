"""Cameras on the MJX backend: MuJoCo Warp's ray-traced renderer inside the jitted scan.

MJX renders only on MuJoCo Warp (`mjx.render`): a render context, made once per program on the
host, holds each camera's rays and the scene's BVH for a fixed number of worlds (`nbatch`).
Each recorded frame refits the BVH to the new poses and renders every camera of every world in
one call, under `vmap` inside the scan (a plain scan over a vmapped render, the way MJX
supports it). The `mjx.Data` that comes out carries Warp's ordering token and must be carried
on.

Images are unpacked on the device straight into what is delivered: RGB from Warp's packed
uint32 to uint8 (MJX's own `get_rgb` makes float32, 4x the memory, of the whole batch), depth
as Warp's planar depth in metres (MJX's `get_depth` divides and clamps it to [0, 1]), and
segmentation as geom ids, -1 elsewhere.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader import observe
from simloader.backends.mjx.runtime import mjx


def refusal(images: Sequence[observe.CameraImage], impl: str) -> Optional[str]:
    """Why implementation `impl` cannot render these camera images, or None."""
    if not images:
        return None
    if impl != "warp":
        return (f"impl={impl!r} cannot render cameras: MJX renders only on MuJoCo Warp; use "
                f"impl='warp' (or 'auto') on a CUDA GPU, or backend='rollout'")
    if any(o.camera_id < 0 for o in images):
        return ("MuJoCo Warp renders the model's cameras, not the free camera (-1); add a "
                "<camera> to the model, or use backend='rollout'")
    sizes: dict[int, set] = {}
    for o in images:
        sizes.setdefault(o.camera_id, set()).add((o.camera.height, o.camera.width))
    for cam, shapes in sizes.items():
        if len(shapes) > 1:
            return (f"camera {cam} is asked at {len(shapes)} sizes {sorted(shapes)}: MuJoCo Warp "
                    f"renders each camera at one size; ask each camera once")
    return None


class Renderer:
    """The cameras of a configuration rendered by MuJoCo Warp, for one program.

    Args:
      model: the MjModel (the render context is built from its geometry and cameras).
      images: the camera images `record` asks for.
      nbatch: worlds per batch (fixed in the render context).
      randomized: the model fields randomized per trajectory (a randomized `cam_fovy` needs
        rays computed per world instead of precomputed).
    """

    def __init__(self, model: mujoco.MjModel, images: Sequence[observe.CameraImage],
                 nbatch: int, randomized: Sequence[str] = ()):
        self.images = tuple(images)
        cams = sorted({o.camera_id for o in images})
        asked = {cam: {o.kind for o in images if o.camera_id == cam} for cam in cams}
        size = {o.camera_id: (o.camera.width, o.camera.height) for o in images}
        self.segmentation = any("segmentation" in kinds for kinds in asked.values())
        # what MuJoCo Warp's render context is made of (the Warp closed loop makes its own)
        self.context_args = dict(
            nworld=nbatch, cam_active=cams, cam_res=[size[c] for c in cams],
            render_rgb=["rgb" in asked[c] for c in cams],
            render_depth=["depth" in asked[c] for c in cams],
            render_seg=["segmentation" in asked[c] for c in cams],
            use_precomputed_rays="cam_fovy" not in randomized)
        # the context lives as long as the program: MJX looks its buffers up by key, and
        # drops them when it is collected
        self.context = mjx.create_render_context(mjm=model, **self.context_args)
        # where each image lies in Warp's packed per-world buffers, by camera's active index
        index = {cam: i for i, cam in enumerate(cams)}
        address = {"rgb": self.context.rgb_adr.numpy(), "depth": self.context.depth_adr.numpy(),
                   "segmentation": self.context.seg_adr.numpy()}
        self.pose = _Pose(model)
        self.slices = {o.key: (o.kind, int(address[o.kind][index[o.camera_id]]),
                               o.camera.height * o.camera.width) for o in images}

    def __call__(self, m: Any, d: Any, model_axes: Any) -> tuple[Any, dict[str, jax.Array]]:
        """Renders every camera of the batched `d`: (d carrying the render's token, {key:
        (nbatch, *shape)}).

        The images show the state `d` holds (the state after the last step, as delivered),
        not the poses `mj_step` left in it, which are those of the step's start: the
        kinematics, and cameras and lights, are brought to the state first. A step recomputes
        all of them from the state, so the physics is unchanged.
        """
        ctx = self.context.pytree()
        d = jax.vmap(self.pose, (model_axes, 0))(m, d)
        d = jax.vmap(mjx.refit_bvh, (model_axes, 0, None))(m, d, ctx)
        if self.segmentation:
            rgb, depth, seg, d = jax.vmap(mjx.render_with_segmentation, (model_axes, 0, None))(
                m, d, ctx)
        else:
            (rgb, depth, d), seg = jax.vmap(mjx.render, (model_axes, 0, None))(m, d, ctx), None
        out = {}
        for o in self.images:
            kind, start, n = self.slices[o.key]
            if kind == "rgb":
                packed = rgb[:, start:start + n]
                # Warp packs each pixel as 0xAABBGGRR read little-endian: red in bits 16-23,
                # blue in 0-7 (MJX's get_rgb reads it the same way)
                channels = [(packed >> shift) & 0xFF for shift in (16, 8, 0)]
                image = jnp.stack(channels, axis=-1).astype(jnp.uint8)
            elif kind == "depth":
                # planar depth in metres, 0 where the ray hits nothing
                image = depth[:, start:start + n] + 0.0
            else:
                hit = seg[:, start:start + n]
                image = jnp.where(hit[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), hit[..., 0], -1)
                image = image.astype(jnp.int32)
            out[o.key] = image.reshape(image.shape[0], *o.shape)
        return d, out



class _Pose:
    """Poses of geoms, cameras and lights at one trajectory's state (`mj_kinematics`,
    `mj_comPos` where a camera or light tracks a centre of mass, `mj_camlight`), on MuJoCo
    Warp, whose MJX binding has no `camlight`: cameras and lights are placed here as
    MuJoCo's mj_camlight places them (MJX-JAX's `smooth.camlight`, extended to lights)."""

    def __init__(self, model: mujoco.MjModel):
        L = mujoco.mjtCamLight
        self.cam = _frames(model.cam_mode, model.cam_bodyid, model.cam_targetbodyid)
        self.light = _frames(model.light_mode, model.light_bodyid, model.light_targetbodyid)
        com = (L.mjCAMLIGHT_TRACKCOM, L.mjCAMLIGHT_TARGETBODYCOM)
        self.needs_com = any(mode in com for mode, _, _ in self.cam + self.light)

    def __call__(self, m: Any, d: Any) -> Any:
        from mujoco.mjx._src import math as mjx_math
        d = mjx.kinematics(m, d)
        if self.needs_com:
            d = mjx.com_pos(m, d)
        if self.cam:
            pos, mat = [], []
            for i, frame in enumerate(self.cam):
                xpos = d.xpos[frame[1]] + mjx_math.rotate(m.cam_pos[i], d.xquat[frame[1]])
                xmat = mjx_math.quat_to_mat(mjx_math.quat_mul(d.xquat[frame[1]], m.cam_quat[i]))
                p, r = _place(frame, xpos, xmat, m.cam_pos0[i], m.cam_poscom0[i],
                              m.cam_mat0[i], d)
                pos.append(p)
                mat.append(r)
            d = d.replace(cam_xpos=jnp.stack(pos), cam_xmat=jnp.stack(mat))
        if self.light:
            pos, direction = [], []
            for i, frame in enumerate(self.light):
                body = frame[1]
                xpos = d.xpos[body] + d.xmat[body] @ m.light_pos[i]
                xdir = d.xmat[body] @ m.light_dir[i]
                p, r = _place(frame, xpos, None, m.light_pos0[i], m.light_poscom0[i], None, d)
                if frame[0] in (mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY,
                                mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM):
                    xdir = -r[:, 2]
                elif frame[0] in (mujoco.mjtCamLight.mjCAMLIGHT_TRACK,
                                  mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM):
                    xdir = m.light_dir0[i]
                pos.append(p)
                direction.append(xdir / jnp.linalg.norm(xdir))
            d = d.tree_replace({"_impl.light_xpos": jnp.stack(pos),
                                "_impl.light_xdir": jnp.stack(direction)})
        return d


def _frames(modes: np.ndarray, bodies: np.ndarray, targets: np.ndarray) -> list:
    """(mode, body, target body) per camera or light; a target mode without a target body is
    fixed, as in MuJoCo."""
    L = mujoco.mjtCamLight
    out = []
    for mode, body, target in zip(modes, bodies, targets):
        if mode in (L.mjCAMLIGHT_TARGETBODY, L.mjCAMLIGHT_TARGETBODYCOM) and target < 0:
            mode = L.mjCAMLIGHT_FIXED
        out.append((int(mode), int(body), int(target)))
    return out


def _place(frame: tuple, xpos: Any, xmat: Any, pos0: Any, poscom0: Any, mat0: Any,
           d: Any) -> tuple[Any, Any]:
    """A camera's or light's global position and orientation in its mode (mj_camlight)."""
    L = mujoco.mjtCamLight
    mode, body, target = frame
    if mode == L.mjCAMLIGHT_TRACK:
        return d.xpos[body] + pos0, mat0
    if mode == L.mjCAMLIGHT_TRACKCOM:
        return d.subtree_com[body] + poscom0, mat0
    if mode in (L.mjCAMLIGHT_TARGETBODY, L.mjCAMLIGHT_TARGETBODYCOM):
        look = d.xpos[target] if mode == L.mjCAMLIGHT_TARGETBODY else d.subtree_com[target]
        z = _normalize(xpos - look)
        x = _normalize(jnp.cross(jnp.array([0.0, 0.0, 1.0], z.dtype), z))
        y = _normalize(jnp.cross(z, x))
        return xpos, jnp.stack([x, y, z], axis=1)
    return xpos, xmat


def _normalize(v: Any) -> Any:
    return v / jnp.maximum(jnp.linalg.norm(v), 1e-15)
