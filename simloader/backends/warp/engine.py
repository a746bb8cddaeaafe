"""One configuration's MuJoCo Warp on one device: a model and data whose arrays never move,
torch views of them, and the step between two control rows captured once as a CUDA graph.

MuJoCo Warp's kernels read and write fixed addresses, so a CUDA graph of them stays valid as long as
nothing moves. Here nothing does: the model, the data, the per-step inputs (the open loop's controls
of a whole batch, or the policy's rows), the step index and the recorded frames are arrays allocated
once, and everything between two control rows (`_step`: noise, the bad-control check, MuJoCo's
clamp, the inputs, MuJoCo Warp's step, the divergence check and restart, the observations, cameras,
the frames) runs as MuJoCo Warp's kernels, the engine's own Warp kernels (`fused`: inputs,
divergence check and restart, frames; few launches, which show on cheap models) and torch
operations, on zero-copy views of them. On a GPU `_step` is captured once as one torch CUDA graph
with MuJoCo Warp's kernels inside (Warp's external capture), in the thread that builds the engine
(the consumer's, at the first batch), on a stream of its own; afterwards the producer thread only
replays it. A training loop's `torch.cuda.synchronize()`, allocations or another dataset's work
cannot invalidate a graph that is never captured again.

Work outside the graph (each batch's reset, per-trajectory model fields, `set_const`, copies of
the outputs) is queued on the same stream, so the device runs everything in order and the host
never waits. Without a GPU (tests, SIMLOADER_WARP_ON_CPU) `_step` runs eagerly on MuJoCo Warp's
CPU kernels: the same code the graph captures.
"""

from __future__ import annotations

import atexit
import contextlib
import weakref
from typing import Any, Optional

import mujoco
import numpy as np
import torch

from simloader import rules
from simloader.backends.warp import cameras, drivers, fused, graphs, model_arrays, runtime
from simloader.backends.warp import episodes as warp_episodes
from simloader.backends.warp import observe as warp_observe
from simloader.backends.warp.options import WarpOptions
from simloader.backends.warp.tables import STATE_ARRAYS, DeviceTables

_PHYSICS = ("time", "qpos", "qvel", "act")  # a FULLPHYSICS row, in order
# the engines alive in this process, released at exit (`_release_all`)
_LIVE: "weakref.WeakSet[WarpSimulation]" = weakref.WeakSet()
_LIVE_GPU: list = []  # non-empty once an engine ran on a GPU in this process


@atexit.register
def _release_all() -> None:
    """At interpreter exit, before the CUDA runtime unloads: every engine's graph destroyed
    while CUDA still answers. Left to garbage collection during teardown, a graph's destructor
    calls into an unloading runtime, and torch's error there aborts the process (a spawned
    DataLoader worker exits through this path)."""
    for engine in list(_LIVE):
        engine.release()
    if _LIVE_GPU and torch.utils.data.get_worker_info() is not None:
        # a DataLoader worker: the blocks its batches lent the main process (CUDA IPC) and
        # that were released there are freed now, not by torch's teardown after CUDA's
        torch.cuda.ipc_collect()


class WarpSimulation:
    """MuJoCo Warp's model and data for `config`, built (and its step graph captured) once.

    Args:
      config: the dataset's configuration.
      options: its resolved `WarpOptions`.
      device: the torch device to simulate on (`cuda:k`, or the CPU for tests).
      on_capture: called after each graph capture (counts them in the dataset's stats).
    """

    def __init__(self, config: Any, options: WarpOptions, device: torch.device,
                 on_capture: Any = None):
        import mujoco_warp as mjw
        self.mjw, self.wp = mjw, runtime.warp()
        # a weak reference: engines are cached per configuration (`backend._ENGINES`, weak
        # keys), and an engine that held its configuration would keep itself alive forever
        self.config = weakref.proxy(config)
        self.options, self.device = options, device
        self.owner: Any = None  # the token of the iterator whose trajectories the data holds
        # MuJoCo clamps `ctrl` columns to each trajectory's own (randomized) ctrlrange
        self.clamps_randomized_ctrlrange = (
            config.randomization is not None
            and any(r.field == "actuator_ctrlrange" for r in config.randomization.resolved)
            and bool(config.control_spec & int(mujoco.mjtState.mjSTATE_CTRL))
            and not config.model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL))
        self.gpu = device.type == "cuda"
        self.wdevice = runtime.warp_device(device)
        # Warp's current device and stream are the process's (`runtime.WARP_LOCK`)
        with runtime.WARP_LOCK, self.wp.ScopedDevice(self.wdevice):
            c = config
            n = c.nbatch
            # MuJoCo Warp's model and data, their arrays never moved, and torch views of them
            model_fields = [f for f in options.per_world if not f.startswith("opt.")]
            self.m = mjw.put_model(c.model, batch_sizes={f: n for f in model_fields})
            for field in options.per_world:  # options: MuJoCo Warp's put_model batches none
                if field.startswith("opt."):
                    self._batch_option(field[4:], n)
            self.m.opt.warn_overflow = 0  # counted per batch instead
            self.d = mjw.make_data(c.model, nworld=n, naconmax=options.naconmax,
                                   njmax=options.njmax)
            self.observations = [o for o in c.observations if not o.rendered]
            names = (*STATE_ARRAYS.values(), "qacc", "sensordata", "overflow",
                     *(name for o in self.observations for name in o.fields()))
            self.views = {name: self._data(name) for name in dict.fromkeys(names)}
            self.model_views = {k: self.wp.to_torch(v)
                                for k, v in model_arrays.arrays(self.m).items()}
            # per-model values and tables every batch gathers from, on the device once
            self.pool_tables = model_arrays.pool_tables(c, options.pooled, device)
            self.tables = DeviceTables(c, device)
            # randomized elements, on the device once (not uploaded every batch)
            self.elements = ({} if c.randomization is None else {
                r.param.key: torch.as_tensor(r.elements, device=device)
                for r in c.randomization.resolved})
            # what the divergence check (`rules.restart_unstable`) leaves finite needs no
            # second look
            self.unchecked = [o.key for o in self.observations
                              if o.floating and not set(o.fields()) <= rules.RESTARTED]
            self.stream = torch.cuda.Stream(device) if self.gpu else None
            self.warp_stream = self.wp.stream_from_torch(self.stream) if self.gpu else None
            self._buffers()
            self.graph: Optional[graphs.Captured] = None
            if self.gpu:
                # what Warp queued so far went on its own stream, which the engine's does not
                # wait on (`queued`): finished before the engine's first step
                self.wp.synchronize_device(self.wdevice)
                self.graph = self._capture()
                if on_capture is not None:
                    on_capture()
        _LIVE.add(self)
        if self.gpu:
            _LIVE_GPU.append(True)

    def release(self) -> None:
        """Waits for the engine's queued work and destroys its graph (the engine is not used
        afterwards)."""
        with runtime.WARP_LOCK:
            if self.graph is not None:
                self.graph.release()
                self.graph = None

    # -- construction ----------------------------------------------------------------------

    def _batch_option(self, name: str, n: int) -> None:
        """Option array `name` with one row per world (MuJoCo Warp batches model arrays by
        `put_model(batch_sizes=)`, options by replacing the array)."""
        shared = getattr(self.m.opt, name)
        batched = self.wp.array(np.broadcast_to(shared.numpy(), (n, *shared.numpy().shape[1:])),
                                dtype=shared.dtype)
        batched._is_batched = True
        setattr(self.m.opt, name, batched)

    def _data(self, name: str) -> torch.Tensor:
        """A (nbatch, -1) torch view of MuJoCo Warp's data array `name` (vectors unrolled;
        booleans as torch bools)."""
        view = self.wp.to_torch(getattr(self.d, name))
        return view.reshape(view.shape[0], -1)

    def _buffers(self) -> None:
        """What `_step` reads and writes besides MuJoCo Warp's arrays: the step index, clamp
        bounds and flags, the driver's rows, the inputs' views, the frames of the
        observations, then the cameras' render context and their frames."""
        c, like = self.config, self.views["qpos"]
        self.t = torch.zeros(1, dtype=torch.int64, device=like.device)
        self.low = torch.full((c.nbatch, c.ncontrol), -torch.inf, dtype=like.dtype,
                              device=like.device)
        self.high = torch.full_like(self.low, torch.inf)
        self.diverged = torch.zeros(c.nbatch, dtype=torch.bool, device=like.device)
        # the open or closed loop's buffers and rows
        self.loop = drivers.driver(c, like, self.tables, self.advance, self.observe_now,
                                   self.stream, self.device)
        self.frames = {}
        for o in self.observations:
            value = warp_observe.value(o, self.views)
            self.frames[o.key] = torch.empty((c.nbatch, c.nframes, *value.shape[1:]),
                                             dtype=value.dtype, device=value.device)
        images = [o for o in c.observations if o.rendered]
        randomized = ({r.field for r in c.randomization.resolved} if c.randomization
                      else set())
        self.cameras = (cameras.Cameras(c.model, c.nbatch, randomized, images, self.m, self.d,
                                        self.wdevice) if images
                        else None)
        if self.cameras is not None:
            self.frames.update(self.cameras.frames(c.nbatch, c.nframes))
        self.obs: dict[str, torch.Tensor] = {}
        # terminate=: the rules checked after every step, and the autoreset
        # (the rules' kinematics of the state now: the next step computes its own)
        self.episodes = (warp_episodes.Episodes(
            c, self.d, lambda: self.mjw.kinematics(self.m, self.d), self.device)
            if c.terminate is not None else None)
        # whether anything reads a step's observations: a policy, or a callable terminate=
        self.read_obs = self.loop.observes or (c.terminate is not None
                                               and c.terminate.check is not None)
        # the engine's own work around MuJoCo Warp's step, as Warp kernels (`fused`)
        self.wt = self.wp.from_torch(self.t)
        self.set_inputs = fused.Inputs(
            self.loop.rows, [(columns, self.views[name], boolean)
                             for columns, name, boolean in self.tables.inputs], self.episodes)
        self.after_step = fused.AfterStep(
            self.views, self.model_views["qpos0"], self.diverged, self.episodes,
            {o.key: (o, self.frames[o.key]) for o in self.observations}, c.record_every)
        self.by_torch = [o for o in self.observations if o.key in self.after_step.rest]

    def _capture(self) -> graphs.Captured:
        """`_step` as one CUDA graph on the engine's stream (`graphs.Captured`: after a first
        eager run; everything it changes is reset per batch), under `runtime.WARP_LOCK` (the
        constructor's)."""
        return graphs.Captured(self.wp, self._step, self.device, self.stream, self.warp_stream)

    # -- per batch -------------------------------------------------------------------------

    @contextlib.contextmanager
    def queued(self):
        """Work queued on the engine's stream (torch's and MuJoCo Warp's), one batch at a time
        in the process (`runtime.WARP_LOCK`: Warp's current stream is the process's). The
        stream scope does not wait on Warp's previous stream (`sync_enter=False`): the
        engine's work is ordered by its own stream alone."""
        with runtime.WARP_LOCK, self.wp.ScopedDevice(self.wdevice):
            if not self.gpu:
                yield
                return
            with torch.cuda.stream(self.stream), \
                    self.wp.ScopedStream(self.warp_stream, sync_enter=False):
                yield

    def set_model(self, model_index: Optional[torch.Tensor],
                  values: dict[str, torch.Tensor]) -> None:
        """Per-trajectory model arrays: each pool array from trajectory i's model
        (`model_index`, (nbatch,)), then the randomized values ({field: (nbatch, nvalues)}
        at `elements`), then what MuJoCo derives from them (`set_const`). Inside `queued`."""
        for field, table in self.pool_tables.items():
            view = self.model_views[field]
            view.copy_(table.index_select(0, model_index).reshape(view.shape))
        plan = self.config.randomization
        if plan is None:
            return
        for r in plan.resolved:
            field, convert = model_arrays.CONVERTED.get(r.field, (r.field, None))
            value = values[r.param.key]
            flat = self.model_views[field].view(self.config.nbatch, -1)
            flat[:, self.elements[r.param.key]] = (
                convert(value) if convert else value).to(flat.dtype)
        if plan.setconst:
            self.mjw.set_const(self.m, self.d)

    def set_bounds(self, low: torch.Tensor, high: torch.Tensor) -> None:
        """The batch's clamp bounds, (nbatch, ncontrol) each: each trajectory's model's
        (`low`, `high`), and with a randomized `actuator_ctrlrange` each trajectory's own
        range on the `ctrl` columns MuJoCo clamps (after `set_model`). Inside `queued`."""
        self.low.copy_(low)
        self.high.copy_(high)
        if self.clamps_randomized_ctrlrange:
            nu = self.config.model.nu
            ranges = self.model_views["actuator_ctrlrange"].reshape(self.config.nbatch, nu, 2)
            limited = self.tables.clamped
            self.low[:, :nu] = torch.where(limited, ranges[..., 0], -torch.inf)
            self.high[:, :nu] = torch.where(limited, ranges[..., 1], torch.inf)

    def claim(self, token: Any) -> bool:
        """The data is the trajectories of the iterator named by `token` from now on; returns
        whether another iterator's were there (this one's are to be taken back)."""
        other = self.owner is not token
        self.owner = token
        return other

    def reset(self, rows: torch.Tensor, fresh: torch.Tensor) -> None:
        """Trajectories `fresh` ((nbatch,) bool) start from their mjSTATE_INTEGRATION `rows`
        ((nbatch, nintegration)); the others continue. Overflow bits start afresh."""
        for name, start, stop in self.tables.integration:
            view = self.views[name]
            value = rows[:, start:stop].to(view.dtype) if view.dtype != torch.bool \
                else rows[:, start:stop] != 0
            view.copy_(torch.where(fresh[:, None], value, view))
        self.views["overflow"].zero_()

    def physics(self) -> torch.Tensor:
        """(nbatch, nstate): the mjSTATE_FULLPHYSICS rows now (a new tensor)."""
        return torch.cat([self.views[name] for name in _PHYSICS], dim=1)

    def integration(self) -> torch.Tensor:
        """(nbatch, nintegration): the mjSTATE_INTEGRATION rows now (a new tensor)."""
        like = self.views["qpos"].dtype
        return torch.cat([self.views[name].to(like) for name, _, _ in self.tables.integration],
                         dim=1)

    def observe_now(self) -> dict[str, torch.Tensor]:
        """The policy's first observations, of the state after the reset: derived fields by
        MuJoCo Warp's forward (the warmstart kept, as mj_forward keeps it), cameras rendered.
        Each a tensor of its own."""
        warmstart = self.views["qacc_warmstart"].clone()
        self.mjw.forward(self.m, self.d)
        self.views["qacc_warmstart"].copy_(warmstart)
        obs = {o.key: warp_observe.value(o, self.views).clone() for o in self.observations}
        if self.cameras is not None:
            # (written into frame 0 too, which the first step rewrites)
            first = torch.zeros(1, dtype=torch.int64, device=self.t.device)
            obs.update({k: v.clone() for k, v in
                        self.cameras.render(self.frames, first, want=True).items()})
        return obs

    def start(self) -> None:
        """Before a batch's first step: step index and flags to zero, then the driver's
        start (the open loop checks and clamps the batch's rows at once)."""
        self.t.zero_()
        self.host_t = 0  # the step index, on the host (a callable terminate= reads it)
        self.diverged.zero_()
        bad = self.loop.start(self.low, self.high)
        if bad is not None:
            self.diverged |= bad

    def finish(self) -> None:
        """After a batch's last step: trajectories whose recorded frames hold a non-finite
        value the divergence check's restart leaves unchecked (`unchecked`) are flagged,
        once per batch over the delivered frames, as the CPU engine checks its records."""
        finite = rules.finite([self.frames[key] for key in self.unchecked], torch)
        if finite is not None:
            self.diverged |= ~finite

    def applied(self) -> torch.Tensor:
        """(nbatch, nstep, ncontrol): the control rows as they acted (a new tensor)."""
        return self.loop.applied()

    def advance(self) -> dict[str, torch.Tensor]:
        """One step, as captured (the graph) or eagerly (the CPU); returns the observations
        after it, {key: (nbatch, *shape)}: views of MuJoCo Warp's arrays or the graph's
        outputs, which the next step rewrites."""
        if self.graph is not None:
            self.graph.replay()
        else:
            self._step()
        c, episodes = self.config, self.episodes
        self.host_t += 1
        if episodes is not None and episodes.rules.check is not None \
                and self.host_t % c.record_every == 0:  # a callable, after each frame
            frame = self.host_t // c.record_every - 1
            obs = {k: v.clone() for k, v in self.obs.items()}
            episodes.external(episodes.rules.checked(obs, frame, c.nbatch), frame)
        return self.obs

    def _step(self) -> None:
        """Everything between two control rows, on the row of step `t` (the driver's
        `row()`: the open loop's, or the policy's with noise, the bad-control check and
        MuJoCo's clamp), the inputs, MuJoCo Warp's step, the divergence check and restart,
        the observations (views of Warp's arrays where they can be; cameras rendered) and
        their frames. Device tensors only, so that one graph serves every step."""
        c = self.config
        bad = self.loop.row(self.t, self.low, self.high)
        if bad is not None:
            self.diverged |= bad
        if self.episodes is not None:  # fresh frames start; their inputs are mj_resetData's
            self.episodes.begin(self.wt)
        self.set_inputs.launch(self.wt)
        self.mjw.step(self.m, self.d)
        # the divergence check and restart, held frames at their fresh state, the frames
        # of the records that are columns of an array
        self.after_step.launch(self.wt, then=self._frame_stage)
        frame = (rules.frame_index(self.t, c.record_every)
                 if self.by_torch or self.cameras is not None else None)
        for o in self.by_torch:
            self.frames[o.key].index_copy_(1, frame, warp_observe.value(o, self.views)[:, None])
        obs = {}
        if self.read_obs:
            obs = {o.key: warp_observe.value(o, self.views) for o in self.observations}
            if self.cameras is not None or (
                    self.episodes is not None and self.episodes.kinematics is not None):
                # rendering, and body rules, bring the poses to the state: the policy (or
                # a callable terminate=) sees what mj_step left in the fields the
                # observations view (poses of the step's start), as without them
                obs = {k: v.clone() for k, v in obs.items()}
        if self.cameras is not None:
            # images go straight into their frames; the policy gets this step's
            obs.update(self.cameras.render(self.frames, frame, want=self.loop.observes))
        if self.episodes is not None:  # the frame's flags; at its end, the resets
            self.episodes.after_step(self.wt)
        self.t += 1
        self.obs = obs

    def _frame_stage(self) -> None:
        """record_kinematics="frame": the forward stages at the state the step left (held
        worlds at their fresh state, restarted ones at theirs), before the frames read it:
        MuJoCo Warp's `forward` where a record needs the acceleration stage, else its `step1`
        (positions, velocities and their sensors, as mj_step1). The next step computes its
        own; none at all by default (`frame_stage` None)."""
        stage = self.config.frame_stage
        if stage is None:
            return
        if stage >= int(mujoco.mjtStage.mjSTAGE_ACC):
            self.mjw.forward(self.m, self.d)
        else:
            self.mjw.step1(self.m, self.d)
