"""The closed-loop driver for MuJoCo Warp: one CUDA graph per step, the policy in torch.

MJX runs MuJoCo Warp through JAX's FFI. Inside the open loop's scan that costs nothing, but a
closed loop returns to Python every step, and one call of a jitted MJX-Warp step cost 14 to 22
ms on the host (H200: cart-pole 4096, humanoid 8192; Warp's callback made about 140 Python
kernel launches per step and captured its graph anew, as buffers inside the step move from
call to call), against 1.5 ms of GPU work for 8192 humanoids. So this driver keeps a MuJoCo Warp
`Model` and `Data` of its own, whose arrays never move, and runs everything between two calls
of the policy (`_step`: noise, MuJoCo's clamp, the inputs, MuJoCo Warp's step, the divergence
check and restart, the observations, the recorded frames) as torch operations and MuJoCo Warp
kernels on zero-copy views of those arrays and on buffers of its own; cameras are rendered
by MuJoCo Warp's renderer after the step, as `render.py` renders them. On a GPU `_step` is
captured once as one CUDA graph (torch's, with MuJoCo Warp's kernels inside) and replayed on
torch's stream every step: per step the host queues the policy, one copy of its controls, one
graph launch and a copy of each observation for the policy; nothing waits on the host, and
the GPU runs policy and physics back to back (humanoid 8192 with a 2x256 MLP: 0.99x the MLP
fused into MJX's scan; `benchmarks/bench_policy_mjx.py`).

Everything else is the MJX closed loop's (`closed_loop.py`), so both compute the same: its
jitted `start` resets the batch (randomization, variants, continuation, noise), MuJoCo Warp's
arrays are loaded from that data, and after the last step the final state goes back to JAX
for `finish` (carry, overflow bits). `_step` mirrors `closed_loop.advance` and
`Pieces.restart_unstable`, in torch. Without a GPU (tests, `SIMLOADER_WARP_ON_CPU`) `_step`
runs eagerly, MuJoCo Warp's CPU kernels included: the same code the graph captures.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from collections.abc import Callable
from typing import Any

import jax
import mujoco
import numpy as np
import torch

from simloader import controls

# mjMAXVAL, as Pieces.restart_unstable
_MAXVAL = 1e10
# torch's dtypes of the delivered images
_TORCH_DTYPES = {np.dtype(np.uint8): torch.uint8, np.dtype(np.float32): torch.float32,
                 np.dtype(np.int32): torch.int32}
# the fields `_restart_unstable` leaves finite in every trajectory
_RESTARTED = frozenset(("time", "qpos", "qvel", "act", "sensordata"))


def supports(observations: Any) -> bool:
    """Whether this driver can run a configuration recording `observations`: only fields
    MuJoCo Warp's Data holds by the name MuJoCo gives them (MJX maps a few from elsewhere);
    cameras render with MuJoCo Warp's own renderer."""
    from mujoco.mjx.third_party import mujoco_warp as mjw
    held = {f.name for f in dataclasses.fields(mjw.Data)}
    return all(set(o.fields()) <= held for o in observations)


@dataclasses.dataclass
class _Slot:
    """Where one MJX leaf lives in MuJoCo Warp: `getattr(owner, name)`."""
    index: int  # the leaf's index in the MJX pytree
    owner: Any
    name: str


def _slots(tree: Any, warp_obj: Any) -> list[_Slot]:
    """The leaves of an MJX `tree` (Model or batched Data, impl="warp") that MuJoCo Warp holds
    as non-empty arrays (the pytree path `contact__dist` is `warp_obj.contact.dist`); fields
    only MJX keeps are left out."""
    import warp as wp
    from mujoco.mjx._src.types import tree_path_to_attr_str
    out = []
    for i, (path, leaf) in enumerate(jax.tree_util.tree_flatten_with_path(tree)[0]):
        *parents, name = tree_path_to_attr_str(path).split("__")
        owner = warp_obj
        for part in parents:
            owner = getattr(owner, part, None) if part else None
        target = getattr(owner, name, None) if owner is not None and name else None
        if isinstance(target, wp.array) and target.size and getattr(leaf, "size", 0):
            out.append(_Slot(i, owner, name))
    return out


def _load(view: torch.Tensor, leaf: Any, slot: _Slot) -> None:
    """Copies a JAX array into a MuJoCo Warp array's torch view, on torch's stream (DLPack
    makes it wait for JAX's)."""
    source = torch.from_dlpack(leaf)
    if source.numel() != view.numel() or source.dtype != view.dtype:
        raise AssertionError(f"simloader: MJX and MuJoCo Warp disagree on {slot.name}: "
                             f"{tuple(source.shape)} {source.dtype} vs "
                             f"{tuple(view.shape)} {view.dtype}")
    view.view(-1).copy_(source.reshape(-1))


class WarpLoop:
    """A configuration's closed loop on MuJoCo Warp, built on its first batch; `run` has
    `ClosedLoop.run`'s contract, with a torch-level policy.

    Args:
      pieces: the configuration's `program.Pieces`.
      closed: its `closed_loop.ClosedLoop` (start, finish, the first batch's blank data).
      model: the MjModel MuJoCo Warp's arrays are made from (the fields that differ per
        trajectory are loaded every batch).
      naconmax, njmax: MuJoCo Warp's buffer sizes, as MJX's data has them.
      device: the JAX device the batch runs on.
    """

    def __init__(self, pieces: Any, closed: Any, model: mujoco.MjModel, naconmax: int,
                 njmax: int, device: jax.Device):
        self.P, self.closed, self.model = pieces, closed, model
        self.noisy = closed.noisy
        self.naconmax, self.njmax = naconmax, njmax
        self.gpu = device.platform == "gpu"
        self.warp_device = f"cuda:{device.local_hardware_id}" if self.gpu else "cpu"
        self.built = False
        # MuJoCo Warp's arrays are the program's, shared by every iterator of the dataset:
        # one batch at a time queues its work on them (the device then runs them in order)
        self.lock = threading.Lock()

    def _build(self, m: Any, d: Any) -> None:
        """MuJoCo Warp's model and data for the batch, torch views of them, and the graph."""
        import warp as wp
        from mujoco.mjx.third_party import mujoco_warp as mjw
        P = self.P
        self.mjw = mjw
        with wp.ScopedDevice(self.warp_device):
            self.wm = mjw.put_model(self.model)
            self.wm.opt.warn_overflow = 0  # counted per batch instead, as in the open loop
            self.wd = mjw.make_data(self.model, nworld=P.nbatch, naconmax=self.naconmax,
                                    njmax=self.njmax)
            # model fields that differ per trajectory (randomized, model lists, variants) get
            # arrays of the batch, loaded every batch; the shared ones are loaded once
            # (`model_axes` is a prefix of the model's tree: None for a whole single model)
            per_trajectory = jax.tree.leaves(jax.tree.map(
                lambda axis, sub: jax.tree.map(lambda _: axis is not None, sub),
                P.model_axes, m, is_leaf=lambda a: a is None))
            leaves = jax.tree.leaves(m)
            self.model_views, self.batch_model_views = [], []
            for slot in _slots(m, self.wm):
                if per_trajectory[slot.index]:
                    shared = getattr(slot.owner, slot.name)
                    if shared.shape[0] != 1:
                        raise AssertionError(f"simloader: model field {slot.name} differs per "
                                             f"trajectory, but MuJoCo Warp has no batch axis "
                                             f"for it")
                    setattr(slot.owner, slot.name, wp.empty(
                        (leaves[slot.index].shape[0], *shared.shape[1:]), dtype=shared.dtype))
                entry = (slot, wp.to_torch(getattr(slot.owner, slot.name)))
                (self.batch_model_views if per_trajectory[slot.index]
                 else self.model_views).append(entry)
            self.data_views = [(slot, wp.to_torch(getattr(slot.owner, slot.name)))
                               for slot in _slots(d, self.wd)]
            for slot, view in self.model_views:
                _load(view, leaves[slot.index], slot)
        field = lambda name: wp.to_torch(getattr(self.wd, name))  # noqa: E731
        self.state = {name: field(name) for name in (
            "time", "qpos", "qvel", "act", "qacc", "qacc_warmstart", "sensordata")}
        self.qpos0 = wp.to_torch(self.wm.qpos0)
        self.inputs = [(c.columns, field(c.name), c.name == "eq_active")
                       for c in P.control_components]
        self.observations = [o for o in P.observations if not o.rendered]
        self.views = {name: field(name) for o in self.observations for name in o.fields()}
        self.images = []  # (observation, kind, torch view of its pixels in Warp's buffers)
        if P.renderer is not None:
            self._render_context(P.renderer)
        # what the divergence check (`_restart_unstable`) leaves finite needs no second look
        self.unchecked = [o.key for o in self.observations
                          if o.floating and not set(o.fields()) <= _RESTARTED]
        self.overflow = field("overflow")
        self._buffers()
        self.graph = self._capture() if self.gpu else None
        self.built = True

    def _render_context(self, renderer: Any) -> None:
        """MuJoCo Warp's render context for the batch's cameras, as `render.Renderer` makes
        MJX's (the same cameras, sizes and buffer layout), and torch views of its images."""
        import warp as wp
        with wp.ScopedDevice(self.warp_device):
            self.rc = self.mjw.create_render_context(mjm=self.model, **renderer.context_args)
        self.needs_com = renderer.pose.needs_com
        buffers = {"rgb": wp.to_torch(self.rc.rgb_data).view(torch.int32),
                   "depth": wp.to_torch(self.rc.depth_data),
                   "segmentation": wp.to_torch(self.rc.seg_data)}
        # R, G, B among a pixel's bytes, on the device (a graph cannot copy an index there)
        self.rgb_bytes = torch.tensor([2, 1, 0], device=buffers["rgb"].device)
        for o in renderer.images:
            kind, start, n = renderer.slices[o.key]
            self.images.append((o, kind, buffers[kind][:, start:start + n]))

    def _buffers(self) -> None:
        """The buffers `_step` reads and writes besides MuJoCo Warp's arrays; one step's
        frame shapes come from the observations of the (blank) data."""
        P, like = self.P, self.state["qpos"]
        self.t = torch.zeros(1, dtype=torch.int64, device=like.device)
        self.u = torch.zeros(P.nbatch, P.shape[2], dtype=like.dtype, device=like.device)
        self.low, self.high = torch.empty_like(self.u), torch.empty_like(self.u)
        self.noise = torch.zeros(P.shape, dtype=like.dtype, device=like.device) \
            if self.noisy else None
        self.control = torch.empty(P.shape, dtype=like.dtype, device=like.device)
        self.diverged = torch.zeros(P.nbatch, dtype=torch.bool, device=like.device)
        # frame j is written by every step of its `record_every` group, the due one last
        self.frames = {}
        for o in self.observations:
            value = o.torch_value(self.views)
            self.frames[o.key] = torch.empty((P.nbatch, P.nframes, *value.shape[1:]),
                                             dtype=value.dtype, device=value.device)
        for o, _, _ in self.images:
            self.frames[o.key] = torch.empty((P.nbatch, P.nframes, *o.shape),
                                             dtype=_TORCH_DTYPES[o.dtype], device=like.device)
        self.obs: dict[str, torch.Tensor] = {}

    def _capture(self) -> Any:
        """`_step` as one CUDA graph, after a first eager run on the capture stream (loads
        MuJoCo Warp's kernels and torch's; what it changes every batch resets). Captured in
        thread-local mode: other threads (the training loop) go on using the GPU meanwhile."""
        import warp as wp
        stream = torch.cuda.Stream(self.state["qpos"].device)
        # Warp's handle of the capture stream, made before the capture (not inside it)
        self.warp_stream = wp.stream_from_torch(stream)
        stream.wait_stream(torch.cuda.current_stream(stream.device))
        with torch.cuda.stream(stream):
            self._step()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
            self._step(capturing=True)
        torch.cuda.current_stream(stream.device).wait_stream(stream)
        return graph

    # -- per batch ---------------------------------------------------------------------

    def run(self, args: tuple, policy: Callable[[dict[str, torch.Tensor], int], torch.Tensor],
            nstep: int, previous: Any) -> tuple[dict[str, Any], Any, Any]:
        """One batch: `policy(observations, t) -> control rows` (torch tensors in and out)
        before every step. Only queues work: nothing here waits for the device."""
        with self.lock:
            return self._run(args, policy, nstep, previous)

    def _run(self, args, policy, nstep, previous):
        P, closed = self.P, self.closed
        with jax.default_matmul_precision("float32"):
            if previous is None:
                control, bounds, seeds, variant, carry, restart = args[4:]
                previous = closed.blank(*args[:5], seeds, variant, carry, restart)
            m, loop, obs, delivered = closed.start(*args, previous)
        d = loop["d"]
        if not self.built:
            self._build(m, d)
        leaves = jax.tree.leaves(m)
        for slot, view in self.batch_model_views:
            _load(view, leaves[slot.index], slot)
        leaves = jax.tree.leaves(d)
        for slot, view in self.data_views:
            _load(view, leaves[slot.index], slot)
        self.low.copy_(torch.from_dlpack(loop["low"]))
        self.high.copy_(torch.from_dlpack(loop["high"]))
        if self.noise is not None:
            self.noise.copy_(torch.from_dlpack(loop["noise"]))
        self.t.zero_()
        self.diverged.zero_()
        obs = {k: torch.from_dlpack(v) for k, v in obs.items()}
        for t in range(nstep):
            self.u.copy_(policy(obs, t))
            if self.graph is not None:
                self.graph.replay()
            else:
                self._step()
            # the observations are views of MuJoCo Warp's arrays (or the graph's outputs),
            # which the next step rewrites: the policy keeps copies of its own
            obs = {k: v.clone() for k, v in self.obs.items()}
        # back to JAX for `finish`: fresh buffers (the next batch overwrites these)
        final = {name: jax.dlpack.from_dlpack(self.state[name].clone())
                 for name in ("time", "qpos", "qvel", "act", "qacc_warmstart")}
        d_final = d.replace(**final, _impl=d._impl.replace(
            overflow=jax.dlpack.from_dlpack(self.overflow.clone())))
        outputs = {**{k: jax.dlpack.from_dlpack(v.clone())
                      for k, v in self.frames.items()},
                   "control": jax.dlpack.from_dlpack(self.control.clone()),
                   "diverged": jax.dlpack.from_dlpack(self.diverged.clone())}
        outputs, carry = closed.finish_outputs(m, d_final, outputs, delivered)
        return outputs, carry, d

    def _step(self, capturing: bool = False) -> None:
        """Everything between two policy calls, on the policy's rows in `self.u` and the
        step index in `self.t` (device tensors, so that one graph serves every step):
        noise, MuJoCo's clamp, the inputs, MuJoCo Warp's step, the divergence check and
        restart, the observations (`self.obs`, cameras rendered; views of Warp's arrays
        where they can be) and their frames. The open
        loop's semantics: a bad row flags its trajectory, and so does an unstable step or a
        non-finite value."""
        P, n = self.P, self.P.nbatch
        with self._warp_scope(capturing):
            u = self.u
            if self.noise is not None:
                u = u + self.noise.index_select(1, self.t)[:, 0]
            self.diverged |= controls.bad_controls(u)
            u = controls.clamp_applied(u, self.low, self.high, torch)
            self.control.index_copy_(1, self.t, u[:, None])
            for columns, target, boolean in self.inputs:
                row = u[:, columns]
                target.view(n, -1).copy_(row != 0 if boolean else row)
            self.mjw.step(self.wm, self.wd)
            self.diverged |= self._restart_unstable()
            obs = {o.key: o.torch_value(self.views) for o in self.observations}
            for key in self.unchecked:
                self.diverged |= ~torch.isfinite(obs[key].reshape(n, -1)).all(dim=1)
            if self.images:
                obs.update(self._render())
        frame = self.t // P.every  # nstep is a multiple of record_every
        for key, value in obs.items():
            self.frames[key].index_copy_(1, frame, value[:, None])
        self.t += 1
        self.obs = obs

    @contextlib.contextmanager
    def _warp_scope(self, capturing: bool) -> Any:
        """MuJoCo Warp's launches on torch's current stream (on a GPU `_step` runs only in
        `_capture`, on its stream); while torch captures its graph, registered with Warp as
        an external capture, which keeps what Warp allocates inside. The stream scope does
        not wait on Warp's previous stream (`sync_enter=False`): a capture that waited on an
        event recorded outside it would be invalidated."""
        import warp as wp
        with wp.ScopedDevice(self.warp_device):
            if not self.gpu:
                yield
                return
            stream = self.warp_stream
            with wp.ScopedStream(stream, sync_enter=False):
                if not capturing:
                    yield
                    return
                wp.capture_begin(stream=stream, external=True, force_module_load=False)
                try:
                    yield
                finally:
                    self.warp_graph = wp.capture_end(stream=stream)

    def _render(self) -> dict[str, torch.Tensor]:
        """Every camera image at the state after the step (restarts included), as
        `render.Renderer` renders it inside MJX's scan: poses brought to the state
        (kinematics, centres of mass where a camera or light tracks one, cameras and lights),
        the BVH refit, one render; then unpacked by torch (depth: a view of Warp's buffer)."""
        mjw = self.mjw
        mjw.kinematics(self.wm, self.wd)
        if self.needs_com:
            mjw.com_pos(self.wm, self.wd)
        mjw.camlight(self.wm, self.wd)
        mjw.refit_bvh(self.wm, self.wd, self.rc)
        mjw.render(self.wm, self.wd, self.rc)
        out = {}
        for o, kind, pixels in self.images:
            if kind == "rgb":
                # each pixel 0xAABBGGRR (see render.py): little-endian bytes B, G, R, A
                image = pixels.view(torch.uint8).reshape(*pixels.shape, 4).index_select(
                    -1, self.rgb_bytes)
            elif kind == "depth":
                image = pixels  # planar depth in metres, 0 where nothing is hit
            else:
                # (object id, object type) per pixel
                geom = int(mujoco.mjtObj.mjOBJ_GEOM)
                image = torch.where(pixels[..., 1] == geom, pixels[..., 0], -1)
            out[o.key] = image.reshape(pixels.shape[0], *o.shape)
        return out

    def _restart_unstable(self) -> torch.Tensor:
        """`Pieces.restart_unstable` on MuJoCo Warp's data, in place: the (nbatch,) rows
        that went unstable, restarted as mj_resetData leaves them. A few fused kernels per
        step (one comparison over the checked fields at once, masked writes in place)."""
        s = self.state
        checked = torch.cat([s["time"][:, None], s["qpos"], s["qvel"], s["act"], s["qacc"]],
                            dim=1)
        # NaN compares False, so `<=` catches NaN, Inf and huge values at once
        stable = ((checked.abs() <= _MAXVAL).all(dim=1)
                  & torch.isfinite(s["sensordata"]).all(dim=1))
        unstable = ~stable
        rows = unstable[:, None]
        s["time"].masked_fill_(unstable, 0)
        torch.where(rows, self.qpos0, s["qpos"], out=s["qpos"])
        for name in ("qvel", "act", "qacc_warmstart", "sensordata"):
            s[name].masked_fill_(rows, 0)
        return unstable
