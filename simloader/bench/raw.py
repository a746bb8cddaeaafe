"""Measuring simloader next to the raw simulators it wraps (`simloader bench` and benchmarks/).

Every method does the same work: `nbatch` trajectories of `nstep` steps from the model's default
state, controls drawn uniformly within `ctrlrange` for every batch, the `mjSTATE_FULLPHYSICS`
state and the sensors recorded after every step. The raw baselines depend on MuJoCo (and JAX
or MuJoCo Warp) alone, not on simloader's code:

- a Python loop stepping one `MjData` (the single-environment reference for speed-ups);
- `mujoco.rollout` on all cores with a persistent thread pool (what the CPU engine wraps);
- a jitted `lax.scan` over `vmap(mjx.step)`, controls drawn in the jitted function (what
  `backend="mjx"` runs);
- a captured `mujoco_warp.step` graph replayed from torch, controls copied in and outputs
  copied out every step (what `backend="warp"` runs).

simloader is timed as delivered: torch tensors in hand (its producer simulating the next batch
meanwhile), after a warm-up batch, blocked on the device after each. Measures run alternately in
one process and the median of the repetitions is reported (`shared/design/performance.md`).
"""

from __future__ import annotations

import concurrent.futures
import copy
import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any, Optional

import mujoco
import numpy as np
import torch
from mujoco import rollout

PYTHON, RAW_ROLLOUT, SIMLOADER_ROLLOUT = ("Python mj_step loop", "mujoco.rollout (raw)",
                                          "simloader cpu")
RAW_MJX, SIMLOADER_MJX = "raw MJX vmap+scan", "simloader mjx"
RAW_WARP, SIMLOADER_WARP = "raw MuJoCo Warp graph, same work", "simloader warp"
# the raw method each simloader method is compared with
RAW_OF = {SIMLOADER_ROLLOUT: RAW_ROLLOUT, SIMLOADER_MJX: RAW_MJX, SIMLOADER_WARP: RAW_WARP}


@dataclasses.dataclass(frozen=True)
class Workload:
    """`nbatch` trajectories of `nstep` steps of the model `name`."""

    name: str
    nbatch: int
    nstep: int

    @property
    def steps(self) -> int:
        return self.nbatch * self.nstep

    def __str__(self) -> str:
        return f"{self.name}:{self.nbatch}x{self.nstep}"


def ctrl_bounds(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-actuator (low, high) of uniform controls: `ctrlrange` if limited, else [-1, 1].

    Written out here rather than taken from simloader's controls, so that the raw baselines
    depend on MuJoCo alone; it is the default range of `simloader.controls.Uniform()`.
    """
    limited = model.actuator_ctrllimited.astype(bool)
    low, high = -np.ones(model.nu), np.ones(model.nu)
    low[limited] = model.actuator_ctrlrange[limited, 0]
    high[limited] = model.actuator_ctrlrange[limited, 1]
    return low, high


# -- the raw baselines ------------------------------------------------------------------------

def default_state(model: mujoco.MjModel) -> np.ndarray:
    """The FULLPHYSICS state `mj_resetData` gives (simloader's `initial_state=None`)."""
    data = mujoco.MjData(model)
    state = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return state


def python_loop(model: mujoco.MjModel, nstep: int, total_steps: int,
                seed: int) -> Callable[[], float]:
    """A measure (seconds per step) of one MjData stepped from Python.

    Trajectories of `nstep` steps (`total_steps` in all, extrapolated per step), state and
    sensors recorded after each step into preallocated arrays, as the batched methods record.
    """
    data = mujoco.MjData(model)
    low, high = ctrl_bounds(model)
    rng = np.random.default_rng(seed)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.empty((nstep, mujoco.mj_stateSize(model, spec)))
    sensordata = np.empty((nstep, model.nsensordata))
    ntraj = max(1, total_steps // nstep)
    length = min(nstep, total_steps)

    def measure() -> float:
        start = time.perf_counter()
        for _ in range(ntraj):
            mujoco.mj_resetData(model, data)
            control = rng.uniform(low, high, size=(length, model.nu))
            for t in range(length):
                data.ctrl[:] = control[t]
                mujoco.mj_step(model, data)
                mujoco.mj_getState(model, data, state[t], spec)
                sensordata[t] = data.sensordata
        return (time.perf_counter() - start) / (ntraj * length)

    measure()  # warm-up
    return measure


def raw_rollout(model: Any, w: Workload, nthread: int, seed: int,
                render: Optional[Callable[[np.ndarray], Any]] = None,
                ) -> tuple[Callable[[int], float], float]:
    """A measure (seconds per step) of back-to-back `mujoco.rollout` calls, and the seconds
    of one call.

    One MjData per thread and a persistent thread pool, fresh uniform controls and fresh
    output arrays every call (as simloader allocates a new tensor per batch). `model`: one
    MjModel, or a list of `w.nbatch` (one per trajectory, as `mujoco.rollout` takes them).
    `render`: also called on each call's states (a `RawRenderers`), as a stream with a camera
    simulates and then renders.
    """
    first = model[0] if isinstance(model, (list, tuple)) else model
    datas = [mujoco.MjData(first) for _ in range(nthread)]
    x0 = np.tile(default_state(first), (w.nbatch, 1))
    low, high = ctrl_bounds(first)
    rng = np.random.default_rng(seed)

    def one_batch():
        control = rng.uniform(low, high, size=(w.nbatch, w.nstep, first.nu))
        state, sensordata = rollout.rollout(model, datas, x0, control, persistent_pool=True)
        return state, sensordata, None if render is None else render(state)

    def measure(nbatches: int) -> float:
        start = time.perf_counter()
        for _ in range(nbatches):
            out = one_batch()
            del out
        return (time.perf_counter() - start) / (nbatches * w.steps)

    one_batch()  # warm-up: starts the pool, touches the code paths
    return measure, measure(1) * w.steps


# -- the benchmark policy (closed-loop baselines and the suite's policy workload) -------------

def mlp(nin: int, nout: int, hidden: int = 256, seed: int = 0) -> torch.nn.Module:
    """The benchmark policy: a torch MLP with two tanh hidden layers of `hidden` units and a
    tanh output (controls in [-1, 1], scaled by `StatePolicy`)."""
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(nin, hidden), torch.nn.Tanh(),
                               torch.nn.Linear(hidden, hidden), torch.nn.Tanh(),
                               torch.nn.Linear(hidden, nout), torch.nn.Tanh())


class StatePolicy:
    """A policy for `SimDataset(policy=)`: the MLP of `(qpos, qvel)`, its [-1, 1] outputs mapped
    onto each actuator's control range (`ctrl_bounds`)."""

    def __init__(self, net: Any, model: mujoco.MjModel):
        self.net = net
        device = next(net.parameters()).device
        low, high = (torch.as_tensor(b, dtype=torch.float32, device=device)
                     for b in ctrl_bounds(model))
        self.mid, self.half = (high + low) / 2, (high - low) / 2

    def __call__(self, obs: dict) -> Any:
        x = torch.cat([obs["qpos"], obs["qvel"]], dim=-1)
        return self.mid + self.half * self.net(x)


# the fields a step reads of the previous one (besides its inputs)
STEP_READS = ("time", "qpos", "qvel", "act", "qacc_warmstart")


class RawBaseline:
    """A raw baseline: calling it simulates one batch and returns once its results are
    ready (blocked on the device); `w` is its workload."""

    w: Workload

    def __call__(self) -> Any:
        raise NotImplementedError

    def measure(self, nbatches: int) -> float:
        """Seconds per step of `nbatches` back-to-back batches."""
        start = time.perf_counter()
        for _ in range(nbatches):
            out = self()
            del out
        return (time.perf_counter() - start) / (nbatches * self.w.steps)

    def _time_first_batch(self) -> None:
        """Sets `shapes`, `first_s` (`compile_s` plus the first batch) and `batch_s` (a warm
        batch), once built."""
        start = time.perf_counter()
        out = self()
        self.shapes = {k: tuple(v.shape) for k, v in out.items()}
        del out
        self.first_s = self.compile_s + time.perf_counter() - start
        self.batch_s = self.measure(1) * self.w.steps


class RawMjx(RawBaseline):
    """The raw MJX-JAX baseline: one jitted function per workload, `f(key, index) -> arrays`.

    What simloader runs on `backend="mjx"` (its Warp engine is `RawWarp`'s).

    Args:
      controls: draw uniform controls for every step (True), or step with none.
      check: after each step, put back rows whose state is not finite (a per-row select over
        what a step reads, as simloader's divergence check does).
      after_step: after each step (and its state recorded), `after_step(mx, d) -> (d,
        {key: per-step output})` on the batched data: rendered images, or a reset and its
        flags; the outputs are returned batch-major with the rest.

    Attributes:
      compile_s: seconds to trace and compile; first_s: to the first batch in hand;
      batch_s: seconds of one (warm) batch; shapes: the output shapes.
    """

    # its row in the tables, and the simloader row it is compared with
    row, simloader_row = RAW_MJX, SIMLOADER_MJX
    engine = "MJX-JAX, a jitted lax.scan over vmap(mjx.step)"

    def __init__(self, model: mujoco.MjModel, w: Workload, seed: int, controls: bool = True,
                 check: bool = False,
                 after_step: Optional[Callable[[Any, Any], tuple[Any, dict]]] = None):
        import jax
        import jax.numpy as jnp
        from simloader.backends.mjx.runtime import mjx  # (imports MJX without its warp print)

        self.w = w
        # alive as long as the compiled function (it may own buffers)
        self.after_step = after_step
        self.mx = mjx.put_model(model, impl="jax")
        self.key = jax.random.key(seed)
        low, high = (jnp.asarray(b, jnp.float32) for b in ctrl_bounds(model))
        step = jax.vmap(mjx.step, in_axes=(None, 0))
        nbatch, nstep, nu = w.nbatch, w.nstep, model.nu
        self.d0 = mjx.make_data(self.mx, impl="jax")  # the state mj_resetData gives

        def batch(mx, d0, key, index):
            ctrl = jax.random.uniform(jax.random.fold_in(key, index), (nstep, nbatch, nu),
                                      minval=low, maxval=high)
            d = jax.tree.map(lambda x: jnp.broadcast_to(x, (nbatch, *x.shape)), d0)

            def body(d, u):
                if controls:
                    d = d.replace(ctrl=u)
                d = step(mx, d)
                if check:
                    ok = jnp.all(jnp.isfinite(d.qpos), axis=-1) & jnp.all(jnp.isfinite(d.qvel),
                                                                          axis=-1)
                    d = d.replace(**{n: jnp.where(ok.reshape((-1,) + (1,) * (getattr(d, n).ndim
                                                                             - 1)),
                                                  getattr(d, n), 0 * getattr(d, n))
                                     for n in STEP_READS})
                state = jnp.concatenate([d.time[:, None], d.qpos, d.qvel, d.act], axis=1)
                extra = {}
                if after_step is not None:
                    d, extra = after_step(mx, d)
                return d, (state, d.sensordata, extra)

            _, (state, sensordata, extra) = jax.lax.scan(body, d, ctrl)
            # batch-major, as simloader delivers
            return {"state": state.swapaxes(0, 1), "sensordata": sensordata.swapaxes(0, 1),
                    "control": ctrl.swapaxes(0, 1),
                    **{k: v.swapaxes(0, 1) for k, v in extra.items()}}

        start = time.perf_counter()
        # the same matmul precision as simloader's (JAX's GPU default is TF32)
        with jax.default_matmul_precision("float32"):
            self.fn = jax.jit(batch).lower(self.mx, self.d0, self.key, 0).compile()
        self.compile_s = time.perf_counter() - start
        self.index = 0
        self._time_first_batch()

    @classmethod
    def matching(cls, model: mujoco.MjModel, w: Workload, seed: int, options: Any) -> RawMjx:
        """The baseline of a simloader dataset resolved to `options` (MJX-JAX has no sizes)."""
        return cls(model, w, seed)

    def __call__(self) -> dict[str, Any]:
        import jax
        out = self.fn(self.mx, self.d0, self.key, self.index)
        self.index += 1
        return jax.block_until_ready(out)


class RawWarp(RawBaseline):
    """The raw MuJoCo Warp baseline: one `mujoco_warp.step` captured once as a CUDA graph and
    replayed, from torch.

    This is what simloader's Warp engine (`backend="warp"`) runs: the public `mujoco_warp`
    package driven from torch, one CUDA graph per step, no MJX and no JAX; so it is the loop
    simloader's `backend="warp"` is compared with (MJX's vendored Warp, through JAX, would be
    another engine). "Same work" (`same_work=True`) is what simloader does besides stepping,
    in the plainest torch a user would write: every batch, controls drawn uniformly within
    `ctrl_bounds` into a (nbatch, nstep, nu) tensor; every step, its controls copied into
    `d.ctrl` before the graph, and the state (time, qpos, qvel, act) and the sensors copied
    into (nbatch, nstep, ...) tensors after it. `same_work=False` only replays the step (the
    ceiling, MuJoCo Warp's `testspeed` setting).

    Args:
      sizes: (naconmax, njmax), MuJoCo Warp's contact pool (whole batch) and constraint rows
        (per world): a simloader dataset's resolved `options.naconmax, options.njmax`, so that
        both run with the same buffers (None: MuJoCo Warp's defaults).
      cameras: also render camera 0 at 64x64 RGB every step and copy its pixels out.
      kinematics: also compute MuJoCo Warp's kinematics of the new state inside the graph,
        after the step (what `after_step` may read).
      continued: the worlds continue from batch to batch (True), or are put back at the model's
        initial state before every batch (False: time, qpos, qvel and act as `make_data` leaves
        them, warmstart zero), as a simloader stream restarts them unless `continue_episodes`.
        The two differ in physics, not bookkeeping: a fallen humanoid's contacts cost MuJoCo
        Warp about 11% more per step than a falling one's (`warp-continued-physics`).
      after_step: with same work, `after_step(self, t)` after step `t`'s state is copied out,
        in torch on the baseline's stream (a reset of the rows a rule ends, for example).

    Attributes:
      compile_s: seconds to build the model and data, compile the kernels and capture the
      graph; first_s: to the first batch in hand; batch_s: seconds of one (warm) batch;
      shapes: the output shapes.
    """

    row, simloader_row = RAW_WARP, SIMLOADER_WARP
    engine = "MuJoCo Warp (mujoco_warp from torch, one captured step graph), same work"

    def __init__(self, model: mujoco.MjModel, w: Workload, seed: int,
                 sizes: tuple[Optional[int], Optional[int]] = (None, None),
                 same_work: bool = True, cameras: bool = False, kinematics: bool = False,
                 after_step: Optional[Callable[[Any, int], None]] = None,
                 continued: bool = False):
        # imported here: the package (and `simloader bench` on the CPU engine) runs
        # without Warp installed
        import mujoco_warp as mjw
        import warp as wp
        wp.config.quiet = True
        start = time.perf_counter()
        self.mjw, self.wp, self.w, self.same_work = mjw, wp, w, same_work
        self.kinematics, self.after_step = kinematics, after_step
        if not torch.cuda.is_available():
            raise RuntimeError("RawWarp needs a CUDA GPU (it replays a CUDA graph), and torch "
                               "sees none")
        self.device = torch.device("cuda", torch.cuda.current_device())
        nworld, nstep = w.nbatch, w.nstep
        with wp.ScopedDevice(f"cuda:{self.device.index}"):
            self.m = mjw.put_model(model)
            # no printf from the kernels (a notice every step the solver hits its iteration
            # limit slows it down): as simloader
            self.m.opt.warn_overflow = 0
            self.d = mjw.make_data(model, nworld=nworld, naconmax=sizes[0], njmax=sizes[1])
            self.rc = (mjw.create_render_context(mjm=model, nworld=nworld, cam_active=[0],
                                                 cam_res=[(64, 64)], render_rgb=[True],
                                                 render_depth=[False], render_seg=[False])
                       if cameras else None)
        t = lambda a: wp.to_torch(a).reshape(nworld, -1)  # noqa: E731
        self.ctrl, self.parts = t(self.d.ctrl), [t(getattr(self.d, f)) for f in
                                                 ("time", "qpos", "qvel", "act")]
        self.sensordata = t(self.d.sensordata)
        self.continued = continued
        self.initial = [p.clone() for p in self.parts]  # before any step
        self.gen = torch.Generator(self.device).manual_seed(seed)
        self.low, self.high = (torch.as_tensor(b, dtype=self.ctrl.dtype, device=self.device)
                               for b in ctrl_bounds(model))
        self.controls = torch.empty((nworld, nstep, model.nu), dtype=self.ctrl.dtype,
                                    device=self.device)
        nstate = sum(p.shape[1] for p in self.parts)
        self.state = torch.empty((nworld, nstep, nstate), device=self.device)
        self.sensors = torch.empty((nworld, nstep, self.sensordata.shape[1]), device=self.device)
        self.pixels = torch.empty((nworld, nstep, 64 * 64), dtype=torch.int32,
                                  device=self.device) if cameras else None
        self.stream = torch.cuda.Stream(self.device)
        self.warp_stream = wp.stream_from_torch(self.stream)
        with torch.cuda.stream(self.stream), wp.ScopedStream(self.warp_stream):
            self._physics()  # compiles the kernels (a capture cannot)
            with wp.ScopedCapture() as capture:
                self._physics()
        self.graph = capture.graph
        self.stream.synchronize()
        self.compile_s = time.perf_counter() - start
        self._time_first_batch()

    @classmethod
    def matching(cls, model: mujoco.MjModel, w: Workload, seed: int, options: Any,
                 **kwargs: Any) -> RawWarp:
        """The same-work baseline of a simloader dataset resolved to `options` (its sizes)."""
        return cls(model, w, seed, sizes=(options.naconmax, options.njmax), **kwargs)

    def _physics(self) -> None:
        mjw = self.mjw
        mjw.step(self.m, self.d)
        if self.kinematics:
            mjw.kinematics(self.m, self.d)
        if self.rc is not None:
            mjw.kinematics(self.m, self.d)
            mjw.camlight(self.m, self.d)
            mjw.refit_bvh(self.m, self.d, self.rc)
            mjw.render(self.m, self.d, self.rc)

    def __call__(self) -> dict[str, torch.Tensor]:
        wp = self.wp
        with torch.cuda.stream(self.stream):
            if not self.continued:
                for part, value in zip(self.parts, self.initial):
                    part.copy_(value)
                wp.to_torch(self.d.qacc_warmstart).zero_()
            if self.same_work:
                torch.rand(self.controls.shape, generator=self.gen, device=self.device,
                           out=self.controls)
                self.controls.mul_(self.high - self.low).add_(self.low)
            for t in range(self.w.nstep):
                if self.same_work:
                    self.ctrl.copy_(self.controls[:, t])
                wp.capture_launch(self.graph, stream=self.warp_stream)
                if self.same_work:
                    torch.cat(self.parts, dim=1, out=self.state[:, t])
                    self.sensors[:, t] = self.sensordata
                    if self.after_step is not None:
                        self.after_step(self, t)
                if self.pixels is not None:
                    self.pixels[:, t] = wp.to_torch(self.rc.rgb_data)
        self.stream.synchronize()
        out = {"state": self.state, "sensordata": self.sensors, "control": self.controls}
        return out if self.pixels is None else {**out, "pixels": self.pixels}


def raw_baseline(backend: str) -> type[RawMjx] | type[RawWarp]:
    """The raw baseline of simloader's GPU engine `backend`: `RawMjx` for "mjx", `RawWarp`
    for "warp"."""
    baselines = {"mjx": RawMjx, "warp": RawWarp}
    if backend not in baselines:
        raise ValueError(f"backend: expected 'mjx' or 'warp', got {backend!r}")
    return baselines[backend]


class RawRenderers:
    """`nthread` threads, each with its own mujoco.Renderer, rendering (nbatch, nframes) FULLPHYSICS
    states into one uint8 array.

    `gl`: the GL platform's module ("egl", "osmesa"), as `MUJOCO_GL` names it, for a process
    that imported mujoco before choosing one (None: the one mujoco chose at import).
    `shadows`, `multisample`: MuJoCo's shadow maps and multisampled offscreen buffer (its
    defaults: on), off as a user turns them off for a software renderer (`offsamples = 0` on a
    copy of the model, the scene's shadow flag)."""

    _gl_lock = threading.Lock()

    def __init__(self, model: mujoco.MjModel, camera: Any, size: int, nthread: int,
                 gl: Optional[str] = None, shadows: bool = True, multisample: bool = True):
        if not multisample:
            model = copy.copy(model)
            model.vis.quality.offsamples = 0
        self.model, self.camera, self.size, self.nthread = model, camera, size, nthread
        self.gl, self.shadows = gl, shadows
        self.local = threading.local()
        self.pool = concurrent.futures.ThreadPoolExecutor(nthread)

    def _renderer(self) -> mujoco.Renderer:
        if self.gl is None:
            return mujoco.Renderer(self.model, self.size, self.size)
        import importlib

        from mujoco.rendering.classic import gl_context
        with self._gl_lock:  # mujoco.Renderer takes its context class from this module
            before = gl_context.GLContext
            gl_context.GLContext = importlib.import_module(f"mujoco.{self.gl}").GLContext
            try:
                return mujoco.Renderer(self.model, self.size, self.size)
            finally:
                gl_context.GLContext = before

    def _rows(self, rows, states, out):
        local = self.local
        if not hasattr(local, "renderer"):
            local.renderer = self._renderer()
            local.data = mujoco.MjData(self.model)
        r, d = local.renderer, local.data
        for i in rows:
            for j in range(states.shape[1]):
                mujoco.mj_setState(self.model, d, states[i, j],
                                   mujoco.mjtState.mjSTATE_FULLPHYSICS)
                mujoco.mj_forward(self.model, d)
                r.update_scene(d, self.camera)
                r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
                r.render(out=out[i, j])

    def __call__(self, states: np.ndarray) -> np.ndarray:
        out = np.empty((*states.shape[:2], self.size, self.size, 3), np.uint8)
        chunks = np.array_split(np.arange(len(states)), 4 * self.nthread)
        for f in [self.pool.submit(self._rows, c, states, out) for c in chunks if len(c)]:
            f.result()
        return out
