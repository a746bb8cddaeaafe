"""One configuration's MuJoCo Warp on one device: a model and data whose arrays never move,
torch views of them, and the step between two control rows captured once as a CUDA graph.

MuJoCo Warp's kernels read and write fixed addresses, so a CUDA graph of them stays valid as
long as nothing moves. Here nothing does: the model, the data, the per-step inputs (the open
loop's controls of a whole batch, or the policy's rows), the step index and the recorded frames
are arrays allocated once, and everything between two control rows (`_step`: noise, the
bad-control check, MuJoCo's clamp, the inputs, MuJoCo Warp's step, the divergence check and
restart, the observations, cameras, the frames) runs as torch operations and MuJoCo Warp
kernels on zero-copy views of them. On a GPU `_step` is captured once as one torch CUDA graph
with MuJoCo Warp's kernels inside (Warp's external capture), in the thread that builds the
engine (the consumer's, at the first batch), on a stream of its own; afterwards the producer
thread only replays it. A training loop's `torch.cuda.synchronize()`, allocations or another
dataset's work cannot invalidate a graph that is never captured again.

Work outside the graph (each batch's reset, per-trajectory model fields, `set_const`, copies of
the outputs) is queued on the same stream, so the device runs everything in order and the host
never waits. Without a GPU (tests, SIMLOADER_WARP_ON_CPU) `_step` runs eagerly on MuJoCo Warp's
CPU kernels: the same code the graph captures.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import weakref
from typing import Any, Optional

import mujoco
import numpy as np
import torch

from simloader import layout, rules
from simloader.backends.warp import cameras, drivers, runtime
from simloader.backends.warp import observe as warp_observe
from simloader.backends.warp.options import CONVERTED, WarpOptions, arrays

S = mujoco.mjtState
# mjSTATE_INTEGRATION components and the MuJoCo Warp data arrays that hold them
_STATE_ARRAYS = {S.mjSTATE_TIME: "time", S.mjSTATE_QPOS: "qpos", S.mjSTATE_QVEL: "qvel",
                 S.mjSTATE_ACT: "act", S.mjSTATE_WARMSTART: "qacc_warmstart",
                 S.mjSTATE_CTRL: "ctrl", S.mjSTATE_QFRC_APPLIED: "qfrc_applied",
                 S.mjSTATE_XFRC_APPLIED: "xfrc_applied", S.mjSTATE_EQ_ACTIVE: "eq_active",
                 S.mjSTATE_MOCAP_POS: "mocap_pos", S.mjSTATE_MOCAP_QUAT: "mocap_quat",
                 S.mjSTATE_USERDATA: "userdata"}
_PHYSICS = ("time", "qpos", "qvel", "act")  # a FULLPHYSICS row, in order
# the engines alive in this process, released at exit (`_release_all`)
_LIVE: "weakref.WeakSet[Engine]" = weakref.WeakSet()
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


class DeviceTables:
    """Per-model host tables on the device, (nmodels, ...) each, gathered per batch by each
    trajectory's model: reset rows (mjSTATE_INTEGRATION as mj_resetData leaves them), undriven
    control columns, clamp bounds, and with variants the initial states from the model."""

    def __init__(self, config: Any, device: torch.device):
        c = config
        f32 = dict(dtype=torch.float32, device=device)
        tables = c.model_tables(layout.INTEGRATION)
        self.reset_rows = torch.as_tensor(tables.reset_rows, **f32)
        self.control_defaults = torch.as_tensor(tables.control_defaults, **f32)
        self.low, self.high = (torch.as_tensor(b, **f32) for b in (tables.low, tables.high))
        self.variant_states = (None if tables.variant_states is None else
                               torch.as_tensor(tables.variant_states, **f32))
        self.physics_cols = torch.as_tensor(layout.component_columns(
            c.model, layout.INTEGRATION, layout.FULLPHYSICS), device=device)
        # the generators' parameters, for draws on the device
        self.control_params = c.control.torch_params(self.reset_rows)
        self.noise_params = (c.policy_noise.torch_params(self.reset_rows)
                             if c.policy_noise is not None else [])
        self.clamped = torch.as_tensor(c.model.actuator_ctrllimited.astype(bool), device=device)


class Engine:
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
        self.gpu = device.type == "cuda"
        self.wdevice = runtime.warp_device(device)
        # Warp's current device and stream are the process's (`runtime.WARP_LOCK`)
        with runtime.WARP_LOCK, self.wp.ScopedDevice(self.wdevice):
            c = config
            n = c.nbatch
            model_fields = [f for f in options.per_world if not f.startswith("opt.")]
            self.m = mjw.put_model(c.model, batch_sizes={f: n for f in model_fields})
            for field in options.per_world:  # options: MuJoCo Warp's put_model batches none
                if field.startswith("opt."):
                    self._batch_option(field[4:], n)
            self.m.opt.warn_overflow = 0  # counted per batch instead
            self.d = mjw.make_data(c.model, nworld=n, naconmax=options.naconmax,
                                   njmax=options.njmax)
            self.model_views = {k: self.wp.to_torch(v) for k, v in arrays(self.m).items()}
            self.views = {name: self._data(name) for name in (
                *_STATE_ARRAYS.values(), "qacc", "sensordata", "overflow")}
            self.pool_tables = self._pool_tables()
            # (data array, first column, end) of each non-empty mjSTATE_INTEGRATION component,
            # in mjtState order: derived once, used by every batch's reset and checkpoint
            self.integration_layout = []
            for bit, name in sorted(_STATE_ARRAYS.items(), key=lambda item: int(item[0])):
                cols = layout.component_columns(c.model, layout.INTEGRATION, int(bit))
                if len(cols):
                    self.integration_layout.append((name, int(cols[0]), int(cols[-1]) + 1))
            # randomized elements, on the device once (not uploaded every batch)
            self.elements = ({} if c.randomization is None else {
                r.param.key: torch.as_tensor(r.elements, device=device)
                for r in c.randomization.resolved})
            self.observations = [o for o in c.observations if not o.rendered]
            for o in self.observations:
                for name in o.fields():
                    self.views.setdefault(name, self._data(name))
            self.cameras = (cameras.Cameras(self, [o for o in c.observations if o.rendered])
                            if any(o.rendered for o in c.observations) else None)
            # what the divergence check (`rules.restart_unstable`) leaves finite needs no
            # second look
            self.unchecked = [o.key for o in self.observations
                              if o.floating and not set(o.fields()) <= rules.RESTARTED]
            self._buffers()
            self.stream = torch.cuda.Stream(device) if self.gpu else None
            self.warp_stream = self.wp.stream_from_torch(self.stream) if self.gpu else None
            self.graph = self.warp_graph = None
            if self.gpu:
                # what Warp queued so far went on its own stream, which the engine's does not
                # wait on (`queued`): finished before the engine's first step
                self.wp.synchronize_device(self.wdevice)
                self.graph = self._capture()
                if on_capture is not None:
                    on_capture()
            # per-model tables every batch gathers from, on the device once
            self.tables = DeviceTables(config, device)
        _LIVE.add(self)
        if self.gpu:
            _LIVE_GPU.append(True)

    def release(self) -> None:
        """Waits for the engine's queued work and destroys its graph (the engine is not used
        afterwards)."""
        with runtime.WARP_LOCK:
            if self.graph is not None:
                self.stream.synchronize()
                self.graph.reset()
                self.graph = self.warp_graph = None

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

    def _pool_tables(self) -> dict[str, torch.Tensor]:
        """For each per-world array that differs across a model pool (lists, variants): the
        values of every model of the pool, (nmodels, ...), gathered per batch by model index."""
        c = self.config
        models = c.models or c.variants
        if models is None:
            return {}
        differing = [f for f in self.options.per_world if f not in self._randomized_fields()]
        tables: dict[str, list] = {f: [] for f in differing}
        with self.wp.ScopedDevice("cpu"):
            for model in models:
                held = arrays(self.mjw.put_model(model))
                for f in differing:
                    tables[f].append(self.wp.to_torch(held[f])[0])
        return {f: torch.stack(rows).to(self.device) for f, rows in tables.items()}

    def _randomized_fields(self) -> set[str]:
        plan = self.config.randomization
        if plan is None:
            return set()
        from simloader.backends.warp.options import SETCONST_OUTPUTS
        out = {CONVERTED.get(r.field, (r.field,))[0] for r in plan.resolved}
        return out | (set(SETCONST_OUTPUTS) if plan.setconst else set())

    def _buffers(self) -> None:
        """What `_step` reads and writes besides MuJoCo Warp's arrays."""
        c, like = self.config, self.views["qpos"]
        self.t = torch.zeros(1, dtype=torch.int64, device=like.device)
        self.low = torch.full((c.nbatch, c.ncontrol), -torch.inf, dtype=like.dtype,
                              device=like.device)
        self.high = torch.full_like(self.low, torch.inf)
        self.loop = drivers.driver(self)  # the open or closed loop's buffers and rows
        self.diverged = torch.zeros(c.nbatch, dtype=torch.bool, device=like.device)
        self.inputs = []  # (columns of a control row, MuJoCo Warp's array, boolean)
        for comp in layout.control_layout(c.model, c.control_spec):
            self.inputs.append((comp.columns, self.views[comp.name], comp.name == "eq_active"))
        self.frames = {}
        for o in self.observations:
            value = warp_observe.value(o, self.views)
            self.frames[o.key] = torch.empty((c.nbatch, c.nframes, *value.shape[1:]),
                                             dtype=value.dtype, device=value.device)
        if self.cameras is not None:
            self.frames.update(self.cameras.frames(c.nbatch, c.nframes))
        self.obs: dict[str, torch.Tensor] = {}

    def _capture(self) -> Any:
        """`_step` as one CUDA graph, after a first eager run on the capture stream (loads
        MuJoCo Warp's kernels and torch's; everything it changes is reset per batch).
        Captured in thread-local mode, with garbage collection paused (a collection inside the
        capture could free device memory), under `runtime.WARP_LOCK` (the constructor's)."""
        stream = self.stream
        stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(stream), \
                self.wp.ScopedStream(self.warp_stream, sync_enter=False):
            self._step()
        graph = torch.cuda.CUDAGraph()
        collecting = gc.isenabled()
        gc.disable()
        try:
            with torch.cuda.graph(graph, stream=stream, capture_error_mode="thread_local"):
                self._step(capturing=True)
        finally:
            if collecting:
                gc.enable()
        torch.cuda.current_stream(self.device).wait_stream(stream)
        return graph

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
            field, convert = CONVERTED.get(r.field, (r.field, None))
            value = values[r.param.key]
            flat = self.model_views[field].view(self.config.nbatch, -1)
            flat[:, self.elements[r.param.key]] = (
                convert(value) if convert else value).to(flat.dtype)
        if plan.setconst:
            self.mjw.set_const(self.m, self.d)

    def reset(self, rows: torch.Tensor, fresh: torch.Tensor) -> None:
        """Trajectories `fresh` ((nbatch,) bool) start from their mjSTATE_INTEGRATION `rows`
        ((nbatch, nintegration)); the others continue. Overflow bits start afresh."""
        for name, start, stop in self.integration_layout:
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
        return torch.cat([self.views[name].to(like) for name, _, _ in self.integration_layout],
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
        self.diverged.zero_()
        self.loop.start()

    def applied(self) -> torch.Tensor:
        """(nbatch, nstep, ncontrol): the control rows as they acted (a new tensor)."""
        return self.loop.applied()

    def advance(self) -> None:
        """One step, as captured (the graph) or eagerly (the CPU)."""
        if self.graph is not None:
            self.graph.replay()
        else:
            self._step()

    def _step(self, capturing: bool = False) -> None:
        """Everything between two control rows, on the row of step `t` (the driver's
        `row()`: the open loop's, or the policy's with noise, the bad-control check and
        MuJoCo's clamp), the inputs, MuJoCo Warp's step, the divergence check and restart,
        the observations (views of Warp's arrays where they can be; cameras rendered) and
        their frames. Device tensors only, so that one graph serves every step."""
        c = self.config
        with self._warp_capture(capturing):
            u = self.loop.row()
            for columns, target, boolean in self.inputs:
                row = u[:, columns]
                target.copy_(row != 0 if boolean else row)
            self.mjw.step(self.m, self.d)
            _, unstable = rules.restart_unstable(self.views, self.model_views["qpos0"], torch)
            self.diverged |= unstable
            obs = {o.key: warp_observe.value(o, self.views) for o in self.observations}
            finite = rules.finite([obs[key] for key in self.unchecked], torch)
            if finite is not None:
                self.diverged |= ~finite
            frame = rules.frame_index(self.t, c.record_every)
            for key, value in obs.items():
                self.frames[key].index_copy_(1, frame, value[:, None])
            if self.cameras is not None:
                if self.loop.observes:
                    # rendering brings the poses to the state: the policy sees what mj_step
                    # left in the fields the observations view (poses of the step's start)
                    obs = {k: v.clone() for k, v in obs.items()}
                # images go straight into their frames; the policy gets this step's
                obs.update(self.cameras.render(self.frames, frame, want=self.loop.observes))
        self.t += 1
        self.obs = obs

    @contextlib.contextmanager
    def _warp_capture(self, capturing: bool):
        """While torch captures its graph, MuJoCo Warp's launches are registered as an
        external capture on the same stream, which keeps what Warp allocates inside."""
        if not capturing:
            yield
            return
        wp = self.wp
        with wp.ScopedStream(self.warp_stream, sync_enter=False):
            wp.capture_begin(stream=self.warp_stream, external=True, force_module_load=False)
            try:
                yield
            finally:
                # kept as long as the engine: Warp's graph object owns what Warp allocated
                # during the capture, which torch's graph reads and writes at every replay
                # (dropped, that memory is freed and reused: illegal accesses, seen on an H200)
                self.warp_graph = wp.capture_end(stream=self.warp_stream)
