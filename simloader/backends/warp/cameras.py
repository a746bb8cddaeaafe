"""Cameras on the Warp engine: MuJoCo Warp's ray-traced renderer inside the step graph.

A render context, made once per engine, holds each camera's rays and the scene's BVH for
`nbatch` worlds. After every step the poses are brought to the state (kinematics, centres of
mass where a camera or light tracks one, cameras and lights: `mj_step` leaves the poses of the
step's start), the BVH is refit and every camera of every world rendered in one call; torch
unpacks the images from Warp's buffers: RGB from Warp's packed 32-bit pixels to uint8, depth as
planar metres (0 where nothing is hit), segmentation as geom ids (-1 elsewhere). A step
recomputes every pose from the state, so the physics is unchanged.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any, Optional

import mujoco
import numpy as np
import torch

from simloader import observe
from simloader.backends.warp import runtime

_TORCH_DTYPES = {np.dtype(np.uint8): torch.uint8, np.dtype(np.float32): torch.float32,
                 np.dtype(np.int32): torch.int32}


def refusal(images: Sequence[observe.CameraImage]) -> Optional[str]:
    """Why MuJoCo Warp cannot render these camera images, or None."""
    if any(o.camera_id < 0 for o in images):
        return ("MuJoCo Warp renders the model's cameras, not the free camera (-1); add a "
                "<camera> to the model, or use backend='cpu'")
    sizes: dict[int, set] = {}
    for o in images:
        sizes.setdefault(o.camera_id, set()).add((o.camera.height, o.camera.width))
    for cam, shapes in sizes.items():
        if len(shapes) > 1:
            return (f"camera {cam} is asked at {len(shapes)} sizes {sorted(shapes)}: MuJoCo Warp "
                    f"renders each camera at one size; ask each camera once")
    return None


class Cameras:
    """The cameras of an engine: MuJoCo Warp's render context and torch views of its images.

    Args:
      model: the MuJoCo model rendered; nworld: its worlds.
      randomized: the model fields randomized per world (cam_fovy among them: each world's
        rays are computed at each render, not once).
      images: the camera images `record` asks for.
      m, d: the engine's MuJoCo Warp model and data (a render brings the data's poses to its
        state).
      wdevice: Warp's name of the engine's device.
    """

    def __init__(self, model: mujoco.MjModel, nworld: int, randomized: Collection[str],
                 images: Sequence[observe.CameraImage], m: Any, d: Any, wdevice: str):
        import mujoco_warp as mjw
        self.mjw, self.wp, self.m, self.d = mjw, runtime.warp(), m, d
        self.images = tuple(images)
        cams = sorted({o.camera_id for o in images})
        asked = {cam: {o.kind for o in images if o.camera_id == cam} for cam in cams}
        size = {o.camera_id: (o.camera.width, o.camera.height) for o in images}
        with self.wp.ScopedDevice(wdevice):
            self.context = mjw.create_render_context(
                mjm=model, nworld=nworld, cam_active=cams,
                cam_res=[size[cam] for cam in cams],
                render_rgb=["rgb" in asked[cam] for cam in cams],
                render_depth=["depth" in asked[cam] for cam in cams],
                render_seg=["segmentation" in asked[cam] for cam in cams],
                use_precomputed_rays="cam_fovy" not in randomized)
        L = mujoco.mjtCamLight
        com = (L.mjCAMLIGHT_TRACKCOM, L.mjCAMLIGHT_TARGETBODYCOM)
        self.needs_com = bool(np.isin(model.cam_mode, com).any()
                              or np.isin(model.light_mode, com).any())
        wp = self.wp
        buffers = {"rgb": wp.to_torch(self.context.rgb_data).view(torch.int32),
                   "depth": wp.to_torch(self.context.depth_data),
                   "segmentation": wp.to_torch(self.context.seg_data)}
        address = {"rgb": self.context.rgb_adr.numpy(), "depth": self.context.depth_adr.numpy(),
                   "segmentation": self.context.seg_adr.numpy()}
        index = {cam: i for i, cam in enumerate(cams)}
        self.packed = {}  # RGB images: Warp views of their packed pixels (uint32)
        self.pixels = []  # (observation, kind, torch view of its pixels in Warp's buffers)
        for o in images:
            start, n = int(address[o.kind][index[o.camera_id]]), o.camera.height * o.camera.width
            self.pixels.append((o, o.kind, buffers[o.kind][:, start:start + n]))
            if o.kind == "rgb":
                self.packed[o.key] = self.context.rgb_data[:, start:start + n]

    def frames(self, nbatch: int, nframes: int) -> dict[str, torch.Tensor]:
        """The recorded frames' buffers, (nbatch, nframes, *shape) per image."""
        return {o.key: torch.empty((nbatch, nframes, *o.shape), dtype=_TORCH_DTYPES[o.dtype],
                                   device=pixels.device) for o, _, pixels in self.pixels}

    def render(self, frames: dict[str, torch.Tensor], frame: torch.Tensor,
               want: bool) -> dict[str, torch.Tensor]:
        """Every camera image at the state now, into frame `frame` (a (1,) device index) of
        `frames`; with `want`, also this step's images, {key: (nbatch, *shape)}, for the
        policy. RGB is unpacked by one kernel from Warp's packed pixels straight into its
        frame (one pass over the images)."""
        mjw, m, d = self.mjw, self.m, self.d
        mjw.kinematics(m, d)
        if self.needs_com:
            mjw.com_pos(m, d)
        mjw.camlight(m, d)
        mjw.refit_bvh(m, d, self.context)
        mjw.render(m, d, self.context)
        out = {}
        for o, kind, pixels in self.pixels:
            n = pixels.shape[0]
            if kind == "rgb":
                stored = frames[o.key]
                _unpack_rgb(self.wp, self.packed[o.key], frame, stored)
                if want:
                    out[o.key] = stored.index_select(1, frame)[:, 0]
                continue
            if kind == "depth":
                image = pixels  # planar depth in metres, 0 where nothing is hit
            else:
                # (object id, object type) per pixel
                geom = int(mujoco.mjtObj.mjOBJ_GEOM)
                image = torch.where(pixels[..., 1] == geom, pixels[..., 0], -1)
            image = image.reshape(n, *o.shape)
            frames[o.key].index_copy_(1, frame, image[:, None])
            if want:
                out[o.key] = image
        return out

_KERNELS: dict = {}


def _unpack_rgb(wp: Any, packed: Any, frame: torch.Tensor, stored: torch.Tensor) -> None:
    """Warp's packed pixels (`packed`, (nworld, npixel) uint32: red in bits 16-23, blue in
    0-7) as uint8 RGB into frame `frame[0]` of `stored` ((nworld, nframes, height, width, 3)).

    Where an image's bytes are whole 32-bit words (npixel a multiple of 4, every usual size)
    a thread turns 4 pixels into 3 words (4 loads, 3 stores: a twelfth of the threads and
    stores of one byte per thread). Other sizes take one thread per pixel."""
    kernels = _kernels(wp)
    n, nframes, npixel = stored.shape[0], stored.shape[1], packed.shape[1]
    frame = wp.from_torch(frame)
    if npixel % 4 == 0:
        words = stored.view(n, nframes, 3 * npixel).view(torch.int32)
        wp.launch(kernels["quads"], dim=(n, npixel // 4),
                  inputs=[packed, frame, wp.from_torch(words, dtype=wp.uint32)])
    else:
        wp.launch(kernels["pixels"], dim=(n, npixel),
                  inputs=[packed, frame, wp.from_torch(stored.view(n, nframes, npixel, 3))])


def _kernels(wp: Any) -> dict:
    """The unpacking kernels, defined on first use (importing simloader imports no Warp)."""
    if _KERNELS:
        return _KERNELS

    @wp.func
    def channel(pixel: wp.uint32, c: int) -> wp.uint32:  # c: 0 red, 1 green, 2 blue
        return (pixel >> wp.uint32(16 - 8 * c)) & wp.uint32(255)

    @wp.kernel
    def unpack_rgb_pixels(packed: wp.array2d(dtype=wp.uint32),
                          frame: wp.array(dtype=wp.int64), out: wp.array4d(dtype=wp.uint8)):
        world, pixel = wp.tid()
        value, f = packed[world, pixel], int(frame[0])
        for c in range(3):
            out[world, f, pixel, c] = wp.uint8(channel(value, c))

    @wp.kernel
    def unpack_rgb_quads(packed: wp.array2d(dtype=wp.uint32),
                         frame: wp.array(dtype=wp.int64), out: wp.array3d(dtype=wp.uint32)):
        # pixels a, b, c, d make the little-endian words rgbr, gbrg, brgb
        world, quad = wp.tid()
        a, b = packed[world, 4 * quad], packed[world, 4 * quad + 1]
        c, d = packed[world, 4 * quad + 2], packed[world, 4 * quad + 3]
        f, w = int(frame[0]), 3 * quad
        out[world, f, w] = (channel(a, 0) | (channel(a, 1) << wp.uint32(8))
                            | (channel(a, 2) << wp.uint32(16)) | (channel(b, 0) << wp.uint32(24)))
        out[world, f, w + 1] = (channel(b, 1) | (channel(b, 2) << wp.uint32(8))
                                | (channel(c, 0) << wp.uint32(16))
                                | (channel(c, 1) << wp.uint32(24)))
        out[world, f, w + 2] = (channel(c, 2) | (channel(d, 0) << wp.uint32(8))
                                | (channel(d, 1) << wp.uint32(16))
                                | (channel(d, 2) << wp.uint32(24)))

    _KERNELS.update(pixels=unpack_rgb_pixels, quads=unpack_rgb_quads)
    return _KERNELS
