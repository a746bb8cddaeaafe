"""Stored states rendered on a GPU by MuJoCo Warp (`StoredDataset(cameras=, backend="warp")`):
the engine's own cameras (`cameras.Cameras`) fed from states read from a store instead of
simulated ones. Every frame of a read batch is one world of one render call: the positions and
mocap poses are written into the worlds, then the poses are brought to them and the cameras
drawn exactly as the engine does after a step (kinematics, centres of mass where tracked,
cameras and lights, the BVH refit, the render). That draw is captured once per world count as
one CUDA graph (`graphs.Captured`) over buffers of its own: a read batch costs a copy in, one
replay and a copy out, not dozens of kernel launches from Python.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Any, Callable

import mujoco
import numpy as np
import torch

from simloader import layout
from simloader.backends.warp import cameras as warp_cameras
from simloader.backends.warp import graphs, runtime

S = mujoco.mjtState
CONTEXTS = 2  # render contexts kept, by world count (a loader's batch size and its last one)


@dataclasses.dataclass
class _Context:
    """One world count's MuJoCo Warp model, data and cameras; the torch views of the data's
    fields a draw writes; the captured draw's input states and output images, its graph, and
    the torch stream it last ran on."""

    m: Any
    d: Any
    cameras: Any
    fields: dict
    frame: torch.Tensor
    states: torch.Tensor
    images: dict
    graph: Any = None
    stream: Any = None


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
        # the model's reference state: what the worlds hold when the draw is captured (valid
        # quaternions), before a batch's states
        data = mujoco.MjData(model)
        self.reference = np.empty(mujoco.mj_stateSize(model, layout.FULLPHYSICS))
        mujoco.mj_getState(model, data, self.reference, layout.FULLPHYSICS)
        # render contexts by world count, the latest CONTEXTS: a render call draws every world
        # of its context, so a batch of 1,024 frames drawn in one grown to 16,384 for another
        # loader cost 16 times its own frames (a loader's batches are one size, but its
        # last one, and two loaders of different batch sizes may take turns)
        self.contexts: collections.OrderedDict[tuple, "_Context"] = \
            collections.OrderedDict()

    def _context(self, nworld: int, dtype: torch.dtype) -> "_Context":
        """A model, data and render context of exactly `nworld` worlds for states of `dtype`,
        with the draw (`_draw`) captured as one CUDA graph over its own input and image
        buffers, made at its first use and kept while among the latest `CONTEXTS` used.
        Called under `runtime.WARP_LOCK`, on the renderer's device."""
        key = (nworld, dtype)
        if key in self.contexts:
            self.contexts.move_to_end(key)
            return self.contexts[key]
        import mujoco_warp as mjw
        wp = runtime.warp()
        wdevice = runtime.warp_device(self.device)
        m = mjw.put_model(self.model)
        d = mjw.make_data(self.model, nworld=nworld)
        cameras = warp_cameras.Cameras(self.model, nworld, (), self.images, m, d, wdevice)
        context = _Context(
            m=m, d=d, cameras=cameras,
            fields={name: wp.to_torch(getattr(d, name)) for name in self.column_index},
            frame=torch.zeros(1, dtype=torch.int64, device=self.device),
            states=torch.as_tensor(self.reference, dtype=dtype, device=self.device
                                   ).expand(nworld, -1).contiguous(),
            images=cameras.frames(nworld, 1))
        # its arrays were filled on Warp's own stream; the graph runs on torch's
        wp.synchronize_device(wdevice)
        stream = torch.cuda.Stream(self.device)
        context.graph = graphs.Captured(wp, lambda: self._draw(context), self.device, stream,
                                        wp.stream_from_torch(stream))
        self.contexts[key] = context
        while len(self.contexts) > CONTEXTS:
            self.contexts.popitem(last=False)[1].graph.release()
        return context

    def _draw(self, context: "_Context") -> None:
        """The states in `context.states` into the worlds (positions and mocap poses), then
        every camera drawn as the engine draws after a step, into `context.images`: device
        work only, captured once per context."""
        for name, cols in self.column_index.items():
            context.fields[name].view(context.states.shape[0], -1)[:] = \
                context.states[:, cols]
        context.cameras.render(context.images, context.frame, want=False)

    def frames(self, states: np.ndarray, model_of: Callable[[int], Any]) -> dict:
        """{image key: (n, nframes, *shape) tensor on the device} of FULLPHYSICS `states`:
        copied into the context's input, the captured draw replayed, the images copied out
        (the next replay rewrites the context's), all on torch's current stream."""
        n, nframes = states.shape[:2]
        worlds = n * nframes
        dtype = getattr(torch, np.dtype(states.dtype).name)
        # through pinned memory (torch's caching host allocator: reused once its copy is
        # done): an asynchronous copy, so that reading the next batch's states on the host
        # runs while this one renders (a copy from pageable memory waited for the GPU)
        host = torch.empty((worlds, states.shape[-1]), dtype=dtype, pin_memory=True)
        host.numpy()[...] = states.reshape(worlds, -1)
        wp = runtime.warp()
        with runtime.WARP_LOCK, wp.ScopedDevice(runtime.warp_device(self.device)):
            context = self._context(worlds, dtype)
            stream = torch.cuda.current_stream(self.device)
            if context.stream is not None and context.stream != stream:
                # the previous batch's draw, on another stream, is done with the buffers
                stream.wait_stream(context.stream)
            context.stream = stream
            context.states.copy_(host, non_blocking=True)
            context.graph.replay()
            images = {k: v.clone() for k, v in context.images.items()}
        return {k: v[:, 0].reshape(n, nframes, *v.shape[2:]) for k, v in images.items()}
