"""Stored states rendered on a GPU by MuJoCo Warp (`StoredDataset(cameras=, backend="warp")`):
the engine's own cameras (`cameras.Cameras`) fed from states read from a store instead of
simulated ones. Every frame of a read batch is one world of one render call: the positions and
mocap poses are written into the worlds, then the poses are brought to them and the cameras
drawn exactly as the engine does after a step (kinematics, centres of mass where tracked,
cameras and lights, the BVH refit, the render).
"""

from __future__ import annotations

import collections
import types
from typing import Any, Callable

import mujoco
import numpy as np
import torch

from simloader import layout
from simloader.backends.warp import cameras as warp_cameras
from simloader.backends.warp import runtime

S = mujoco.mjtState
CONTEXTS = 2  # render contexts kept, by world count (a loader's batch size and its last one)


class StoredRenderer:
    """MuJoCo Warp's renderer for stored states of one model, on `device` (default: the
    current CUDA device); its worlds grow to the largest read batch (frames x trajectories).

    Raises:
      ValueError: no CUDA device; the free camera; per-trajectory models (randomized
        geometry, variants or model lists render on the CPU renderer).
    """

    def __init__(self, model: mujoco.MjModel, images: Any, device: Any, randomized: bool):
        if not torch.cuda.is_available():
            raise ValueError("backend='warp' renders stored states on a CUDA GPU, and this "
                             "machine has none; use backend='cpu' (the CPU renderer, in each "
                             "DataLoader worker)")
        why = warp_cameras.refusal(images)
        if why is not None:
            raise ValueError(f"cameras: {why}")
        if randomized:
            raise ValueError("backend='warp': this store's trajectories have models of their "
                             "own (randomized parameters, variants or a model list), which "
                             "MuJoCo Warp's renderer on read does not take yet; use "
                             "backend='cpu'")
        self.model, self.images = model, tuple(images)
        self.device = torch.device(device if device is not None else "cuda")
        if self.device.type != "cuda":
            raise ValueError(f"device: backend='warp' renders on a CUDA device, got {device!r}")
        if self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        # the state's columns of each field a picture needs (the model has), on the device
        # once (not a host-to-device copy a batch)
        columns = {name: layout.component_columns(model, layout.FULLPHYSICS, spec)
                   for name, spec in (("qpos", S.mjSTATE_QPOS),
                                      ("mocap_pos", S.mjSTATE_MOCAP_POS),
                                      ("mocap_quat", S.mjSTATE_MOCAP_QUAT))}
        self.column_index = {name: torch.as_tensor(cols, dtype=torch.int64, device=self.device)
                             for name, cols in columns.items() if len(cols)}
        # render contexts by world count, the latest CONTEXTS: a render call draws every world
        # of its context, so a batch of 1,024 frames drawn in one grown to 16,384 for another
        # loader cost 16 times its own frames (a loader's batches are one size, but its
        # last one, and two loaders of different batch sizes may take turns)
        self.contexts: collections.OrderedDict[int, types.SimpleNamespace] = \
            collections.OrderedDict()
        self.streams: dict[int, Any] = {}  # Warp's handles of torch's streams

    def _context(self, nworld: int) -> types.SimpleNamespace:
        """A model, data and render context of exactly `nworld` worlds, made at its first
        use and kept while among the latest `CONTEXTS` used."""
        if nworld in self.contexts:
            self.contexts.move_to_end(nworld)
            return self.contexts[nworld]
        import mujoco_warp as mjw
        wp = runtime.warp()
        wdevice = runtime.warp_device(self.device)
        with wp.ScopedDevice(wdevice):
            m = mjw.put_model(self.model)
            d = mjw.make_data(self.model, nworld=nworld)
            config = types.SimpleNamespace(model=self.model, nbatch=nworld, randomization=None)
            cameras = warp_cameras.Cameras(config, self.images, m, d, wdevice)
        context = types.SimpleNamespace(
            m=m, d=d, cameras=cameras,
            fields={name: wp.to_torch(getattr(d, name)) for name in self.column_index},
            frame=torch.zeros(1, dtype=torch.int64, device=self.device))
        # its arrays were filled on Warp's own stream; the renders run on torch's
        wp.synchronize_device(wdevice)
        self.contexts[nworld] = context
        while len(self.contexts) > CONTEXTS:
            self.contexts.popitem(last=False)
        return context

    def frames(self, states: np.ndarray, model_of: Callable[[int], Any]) -> dict:
        """{image key: (n, nframes, *shape) tensor on the device} of FULLPHYSICS `states`."""
        n, nframes = states.shape[:2]
        worlds = n * nframes
        context = self._context(worlds)
        # through pinned memory (torch's caching host allocator: reused once its copy is
        # done): an asynchronous copy, so that reading the next batch's states on the host
        # runs while this one renders (a copy from pageable memory waited for the GPU)
        host = torch.empty((worlds, states.shape[-1]),
                           dtype=getattr(torch, np.dtype(states.dtype).name), pin_memory=True)
        host.numpy()[...] = states.reshape(worlds, -1)
        flat = host.to(self.device, non_blocking=True)
        wp = runtime.warp()
        # MuJoCo Warp's kernels on torch's current stream, after the copy and the gathers
        # queued there, and before whatever the reader queues there next (Warp's current
        # stream is the process's: under the engines' lock)
        with runtime.WARP_LOCK, wp.ScopedDevice(runtime.warp_device(self.device)), \
                wp.ScopedStream(self._warp_stream(), sync_enter=False):
            for name, cols in self.column_index.items():
                context.fields[name].view(worlds, -1)[:] = flat[:, cols]
            buffers = context.cameras.frames(worlds, 1)
            context.cameras.render(buffers, context.frame, want=False)
        return {k: v[:, 0].reshape(n, nframes, *v.shape[2:]) for k, v in buffers.items()}

    def _warp_stream(self) -> Any:
        """Warp's handle of torch's current stream on the device (made once per stream)."""
        stream = torch.cuda.current_stream(self.device)
        key = stream.cuda_stream
        if key not in self.streams:
            self.streams[key] = runtime.warp().stream_from_torch(stream)
        return self.streams[key]
