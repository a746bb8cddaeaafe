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

import dataclasses
import math
import os
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
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


def cpu_count() -> int:
    """CPU cores this process may run on (what simloader's CPU engine uses)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def device_name(device: torch.device) -> str:
    """What a torch device is, for the "runs on" column ("NVIDIA H200", "CPU")."""
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"


# -- timing -----------------------------------------------------------------------------------

def sync() -> None:
    """Waits for the GPU work queued on torch's current stream.

    Not a device-wide `torch.cuda.synchronize()`: simloader orders each delivered batch before
    the consumer's stream, so that stream is all a timing of delivered batches must wait for;
    a device-wide synchronize would also wait for the batches the producer thread simulates
    ahead, and time them twice.
    """
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.current_stream().synchronize()


def drain() -> None:
    """Waits until the work already dispatched to the devices has run.

    simloader's MJX producer dispatches batches ahead; those an iterator was closed on still
    run on the device and would slow whatever is timed next. Devices run their work in order,
    so a tiny computation on each, waited for, waits for them.
    """
    sync()
    jax = sys.modules.get("jax")
    if jax is not None:
        for device in jax.local_devices():
            jax.block_until_ready(jax.device_put(0, device) + 1)


def progress(iterable: Iterable, desc: str = "", total: Optional[int] = None) -> Iterable:
    """A tqdm progress bar on stderr (sparse when stderr is a log file)."""
    from tqdm import tqdm
    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr,
                mininterval=1.0 if sys.stderr.isatty() else 30.0)


def interleave(measures: dict[str, Callable[[], float]], repeats: int,
               desc: str = "") -> dict[str, float]:
    """The median of each measure's result, the measures run alternately `repeats` times.

    Each measure times its own steady part (warm-up excluded) and returns seconds per
    simulated step. The order is reversed every repetition, so that drift in the machine
    (clocks, caches, other load) touches every measure alike.
    """
    times: dict[str, list[float]] = {name: [] for name in measures}
    order = list(measures)
    for rep in progress(range(repeats), desc=desc):
        for name in order if rep % 2 == 0 else reversed(order):
            times[name].append(measures[name]())
    return {name: statistics.median(t) for name, t in times.items()}


def batches_for(batch_s: float, min_batches: int, min_seconds: float) -> int:
    """Timed batches per repetition: `min_batches`, or more to last `min_seconds`."""
    return max(min_batches, math.ceil(min_seconds / max(batch_s, 1e-9)))


@dataclasses.dataclass
class Stream:
    """One pass over a dataset: `first_s` to the first batch, `steady_s` for the rest."""

    first_s: float
    steady_s: float
    last: Optional[dict[str, torch.Tensor]] = None


def time_stream(ds: Iterable[dict[str, torch.Tensor]], nbatches: int,
                keep_last: bool = False) -> Stream:
    """Delivered throughput of a dataset: `nbatches` batches after the first, tensors in hand.

    A fresh iterator per call: simloader's producer thread starts with it and stops at
    `close`, and the device is drained, so nothing simulates while another measure runs. The
    first batch, which pays for threads, compilation and the empty prefetch queue, is timed
    apart; the steady part runs from holding the first batch to holding the last, blocked on
    the device after each.
    """
    it = iter(ds)
    try:
        start = time.perf_counter()
        batch = next(it)
        sync()
        first = time.perf_counter()
        for _ in range(nbatches):
            del batch  # release a (possibly multi-GB) batch before the next arrives
            batch = next(it)
            sync()
        return Stream(first - start, time.perf_counter() - first, batch if keep_last else None)
    finally:
        it.close()
        drain()


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


def raw_rollout(model: Any, w: Workload, nthread: int,
                seed: int) -> tuple[Callable[[int], float], float]:
    """A measure (seconds per step) of back-to-back `mujoco.rollout` calls, and the seconds
    of one call.

    One MjData per thread and a persistent thread pool, fresh uniform controls and fresh
    output arrays every call (as simloader allocates a new tensor per batch). `model`: one
    MjModel, or a list of `w.nbatch` (one per trajectory, as `mujoco.rollout` takes them).
    """
    first = model[0] if isinstance(model, (list, tuple)) else model
    datas = [mujoco.MjData(first) for _ in range(nthread)]
    x0 = np.tile(default_state(first), (w.nbatch, 1))
    low, high = ctrl_bounds(first)
    rng = np.random.default_rng(seed)

    def one_batch():
        control = rng.uniform(low, high, size=(w.nbatch, w.nstep, first.nu))
        return rollout.rollout(model, datas, x0, control, persistent_pool=True)

    def measure(nbatches: int) -> float:
        start = time.perf_counter()
        for _ in range(nbatches):
            state, sensordata = one_batch()
            del state, sensordata
        return (time.perf_counter() - start) / (nbatches * w.steps)

    one_batch()  # warm-up: starts the pool, touches the code paths
    return measure, measure(1) * w.steps


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
                 after_step: Optional[Callable[[Any, int], None]] = None):
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
    def matching(cls, model: mujoco.MjModel, w: Workload, seed: int, options: Any) -> RawWarp:
        """The same-work baseline of a simloader dataset resolved to `options` (its sizes)."""
        return cls(model, w, seed, sizes=(options.naconmax, options.njmax))

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


# -- simloader, measured the same way ---------------------------------------------------------

class SimloaderMeasure:
    """A simloader dataset, warmed up by one pass (which compiles on MJX), then measured.

    Attributes:
      ds: the dataset; first_s: seconds to its first batch (compilation included);
      compile_s: of which compiling; shapes, device: of the delivered batch.
    """

    def __init__(self, model: mujoco.MjModel, w: Workload, backend: str, seed: int,
                 **options: Any):
        import simloader  # imported late: benchmarks/ put their checkout first on sys.path
        self.w = w
        options = {"control": simloader.controls.Uniform(), **options}
        self.ds = simloader.SimDataset(model, backend=backend, nbatch=w.nbatch, nstep=w.nstep,
                                       seed=seed, **options)
        first = time_stream(self.ds, 0, keep_last=True)
        self.first_s = first.first_s
        self.compile_s = self.ds.stats.get("compile_s", 0.0)
        self.shapes = {k: tuple(v.shape) for k, v in first.last.items() if k != "params"}
        self.device = first.last["control"].device
        del first

    def measure(self, nbatches: int) -> float:
        """Seconds per step of `nbatches` delivered batches after a fresh iterator's first."""
        return time_stream(self.ds, nbatches).steady_s / (nbatches * self.w.steps)


# -- tables and plots -------------------------------------------------------------------------

def ns(seconds_per_step: float) -> str:
    return f"{seconds_per_step * 1e9:,.1f}" if seconds_per_step < 1e-7 else \
        f"{seconds_per_step * 1e9:,.0f}"


def rate(steps_per_second: float) -> str:
    return f"{steps_per_second / 1e6:,.2f}M"


def ratio(x: Optional[float]) -> str:
    return "-" if x is None else f"{x:.3f}"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table, columns padded for reading in a terminal too."""
    cells = [list(map(str, headers))] + [list(map(str, r)) for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    line = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "| " + " | ".join("-" * w for w in widths) + " |"]
                     + [line(r) for r in cells[1:]])


HEADERS = ["workload", "nbatch x nstep", "method", "runs on", "ns/step", "steps/s",
           "throughput / raw", "vs Python loop"]


def method_rows(w: Workload, s_per_step: dict[str, float], runs_on: dict[str, str],
                raw_of: dict[str, str], python: Optional[str]) -> list[list[str]]:
    """Rows of `HEADERS`, one per method, in the order of `s_per_step`.

    Args:
      s_per_step: seconds per simulated step of each method.
      runs_on: where each method runs ("16 cores", "NVIDIA H200").
      raw_of: for a simloader method, the raw method it is compared to (throughput ratio).
      python: the method that is the single-environment Python loop, for speed-ups.
    """
    base = s_per_step.get(python)
    rows = []
    for method, s in s_per_step.items():
        raw = s_per_step.get(raw_of.get(method, method)) if method in raw_of or \
            method in raw_of.values() else None
        rows.append([w.name, f"{w.nbatch} x {w.nstep}", method, runs_on[method], ns(s),
                     rate(1 / s), ratio(raw / s if raw else None),
                     f"{base / s:,.1f}x" if base else "-"])
    return rows


def bar_plot(path: str, title: str, s_per_step: dict[str, float]) -> None:
    """A horizontal bar chart of steps/s per method (log scale), raw baselines hatched."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(s_per_step)
    fig, ax = plt.subplots(figsize=(7, 0.6 * len(names) + 1.5))
    rates = [1 / s_per_step[n] for n in names]
    raw = [n in RAW_OF.values() or n == PYTHON for n in names]
    bars = ax.barh(names, rates, color=["lightgray" if r else "tab:blue" for r in raw],
                   edgecolor=["dimgray" if r else "tab:blue" for r in raw],
                   hatch=["//" if r else "" for r in raw])
    for value, bar in zip(rates, bars):
        ax.annotate(f" {value:,.3g}", (bar.get_width(), bar.get_y() + bar.get_height() / 2),
                    va="center")
    ax.set_xscale("log")
    # log-scale bars start at the left edge: put it well below the slowest, so lengths compare
    ax.set_xlim(min(rates) / 10, max(rates) * 3)
    ax.invert_yaxis()
    ax.set_xlabel("simulated steps per second (log)")
    ax.set_title(title)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# -- `simloader bench` ------------------------------------------------------------------------

def compare(model: mujoco.MjModel, w: Workload, backends: Sequence[str], *, repeats: int = 3,
            min_batches: int = 3, min_seconds: float = 2.0, python_steps: int = 5000,
            seed: int = 0) -> tuple[dict[str, float], dict[str, str], list[str]]:
    """Measures the chosen backends next to their raw simulators and a Python loop.

    Returns:
      (seconds per step of each method, where each runs, notes).
    """
    measures: dict[str, Callable[[], float]] = {}
    runs_on = {PYTHON: "1 core"}
    notes = []
    for backend in backends:
        if backend == "cpu":
            raw, batch_s = raw_rollout(model, w, cpu_count(), seed)
            # all the cores, as the raw rollout: nothing trains beside this measurement
            sim = SimloaderMeasure(model, w, "cpu", seed, nthread=cpu_count())
            n = batches_for(batch_s, min_batches, min_seconds)
            measures[RAW_ROLLOUT] = lambda raw=raw, n=n: raw(n)
            measures[SIMLOADER_ROLLOUT] = lambda sim=sim, n=n: sim.measure(n)
            runs_on[RAW_ROLLOUT] = runs_on[SIMLOADER_ROLLOUT] = f"{cpu_count()} cores"
        elif backend in ("mjx", "warp"):
            sim = SimloaderMeasure(model, w, backend, seed)
            Raw = raw_baseline(backend)
            raw = Raw.matching(model, w, seed, sim.ds.config.options)
            notes.append(f"{backend}: raw: {Raw.engine}")
            n = batches_for(raw.batch_s, min_batches, min_seconds)
            measures[Raw.row] = lambda raw=raw, n=n: raw.measure(n)
            measures[Raw.simloader_row] = lambda sim=sim, n=n: sim.measure(n)
            runs_on[Raw.row] = runs_on[Raw.simloader_row] = device_name(sim.device)
            notes.append(f"{backend}: compiled in {raw.compile_s:.1f} s (raw) and "
                         f"{sim.compile_s:.1f} s (simloader, first batch after "
                         f"{sim.first_s:.1f} s)")
        else:
            raise ValueError(f"backends: expected 'cpu', 'mjx' or 'warp', got {backend!r}")
    measures[PYTHON] = python_loop(model, w.nstep, python_steps, seed)
    return interleave(measures, repeats, desc=f"{w} x{repeats}"), runs_on, notes
