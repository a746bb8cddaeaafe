"""The closed-loop driver for MuJoCo Warp: one CUDA graph per step, the policy in torch.

MJX runs MuJoCo Warp through JAX's FFI. Inside the open loop's scan that costs nothing, but a
closed loop returns to Python every step, and one call of a jitted MJX-Warp step cost 14 to 22
ms on the host (H200: cart-pole 4096, humanoid 8192; Warp's callback made about 140 Python
kernel launches per step and captured its graph anew, as buffers inside the step move from
call to call), against 1.5 ms of GPU work for 8192 humanoids. So this driver keeps a MuJoCo Warp
`Model` and `Data` of its own, whose arrays never move, captures MuJoCo Warp's step on them as
one CUDA graph once, and replays it on torch's stream every step. The policy, the inputs it
sets and everything a step checks and records are torch operations on zero-copy views of
those arrays, queued on the same stream: no host synchronisation, and the GPU runs policy and
physics back to back (humanoid 8192 with a 2x256 MLP: 4.88M steps/s, 0.97x the MLP fused
into MJX's scan; `benchmarks/bench_policy_mjx.py`).

Everything else is the MJX closed loop's (`closed_loop.py`), so both compute the same: its
jitted `start` resets the batch (randomization, variants, continuation, noise), MuJoCo Warp's
arrays are loaded from that data, and after the last step the final state goes back to JAX
for `finish` (carry, overflow bits). What happens between policy and physics mirrors
`closed_loop.advance` and `Pieces.restart_unstable`, in torch. Without a GPU (tests,
`SIMLOADER_WARP_ON_CPU`) MuJoCo Warp's CPU kernels run each step directly, without a graph.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from typing import Any

import jax
import mujoco
import torch

from simloader import controls

# mjMAXVAL, as Pieces.restart_unstable
_MAXVAL = 1e10
# the fields `_restart_unstable` leaves finite in every trajectory
_RESTARTED = frozenset(("time", "qpos", "qvel", "act", "sensordata"))


def supports(observations: Any) -> bool:
    """Whether this driver can run a configuration recording `observations`: no cameras
    (rendered inside MJX's jitted steps) and only fields MuJoCo Warp's Data holds by the name
    MuJoCo gives them (MJX maps a few, e.g. efc_force, from elsewhere)."""
    from mujoco.mjx.third_party import mujoco_warp as mjw
    held = {f.name for f in dataclasses.fields(mjw.Data)}
    return all(not o.rendered and set(o.fields()) <= held for o in observations)


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
            self.graph = None
            if self.gpu:
                # a first step loads the kernels (on data every batch overwrites); the step is
                # then captured on a stream of its own (the default stream cannot capture)
                stream = wp.Stream(self.warp_device)
                with wp.ScopedStream(stream):
                    mjw.step(self.wm, self.wd)
                    with wp.ScopedCapture(stream=stream) as capture:
                        mjw.step(self.wm, self.wd)
                wp.synchronize_stream(stream)
                self.graph = capture.graph
        field = lambda name: wp.to_torch(getattr(self.wd, name))  # noqa: E731
        self.state = {name: field(name) for name in (
            "time", "qpos", "qvel", "act", "qacc", "qacc_warmstart", "sensordata")}
        self.qpos0 = wp.to_torch(self.wm.qpos0)
        self.inputs = [(c.columns, field(c.name), c.name == "eq_active")
                       for c in P.control_components]
        self.observations = [o for o in P.observations if not o.rendered]
        self.views = {name: field(name) for o in self.observations for name in o.fields()}
        # what the divergence check (`_restart_unstable`) leaves finite needs no second look
        self.unchecked = [o.key for o in self.observations
                          if o.floating and not set(o.fields()) <= _RESTARTED]
        self.overflow = field("overflow")
        self.built = True

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
        low, high = (torch.from_dlpack(loop[k]) for k in ("low", "high"))
        noise = torch.from_dlpack(loop["noise"]) if "noise" in loop else None
        obs = {k: torch.from_dlpack(v) for k, v in obs.items()}
        frames = {k: torch.empty((P.nbatch, P.nframes, *v.shape[1:]), dtype=v.dtype,
                                 device=v.device) for k, v in obs.items()}
        control = torch.empty(P.shape, dtype=low.dtype, device=low.device)
        diverged = torch.zeros(P.nbatch, dtype=torch.bool, device=low.device)
        stream = None
        if self.graph is not None:
            import warp as wp
            stream = wp.stream_from_torch(torch.cuda.current_stream(low.device))
        for t in range(nstep):
            u = policy(obs, t).to(low.dtype)
            if noise is not None:
                u = u + noise[:, t]
            # as the open loop: a bad row flags its trajectory, MuJoCo's clamp is applied
            diverged |= controls.bad_controls(u)
            u = controls.clamp_applied(u, low, high, torch)
            control[:, t] = u
            for columns, target, boolean in self.inputs:
                row = u[:, columns]
                target.view(P.nbatch, -1).copy_(row != 0 if boolean else row)
            self._physics(stream)
            diverged |= self._restart_unstable()
            obs = {o.key: o.torch_value(self.views) for o in self.observations}
            for key in self.unchecked:
                value = obs[key]
                diverged |= ~torch.isfinite(value.reshape(P.nbatch, -1)).all(dim=1)
            # frame j holds the values after step (j + 1) * every
            if t % P.every == P.every - 1:
                for key, value in obs.items():
                    frames[key][:, t // P.every] = value
        # back to JAX for `finish`: fresh buffers (the next batch overwrites MuJoCo Warp's)
        final = {name: jax.dlpack.from_dlpack(self.state[name].clone())
                 for name in ("time", "qpos", "qvel", "act", "qacc_warmstart")}
        d_final = d.replace(**final, _impl=d._impl.replace(
            overflow=jax.dlpack.from_dlpack(self.overflow.clone())))
        outputs = {**{k: jax.dlpack.from_dlpack(v) for k, v in frames.items()},
                   "control": jax.dlpack.from_dlpack(control),
                   "diverged": jax.dlpack.from_dlpack(diverged)}
        outputs, carry = closed.finish_outputs(m, d_final, outputs, delivered)
        return outputs, carry, d

    def _physics(self, stream: Any) -> None:
        if self.graph is not None:
            import warp as wp
            wp.capture_launch(self.graph, stream=stream)
        else:
            import warp as wp
            with wp.ScopedDevice(self.warp_device):
                self.mjw.step(self.wm, self.wd)

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
