"""MJX backend: MuJoCo XLA (JAX) on the GPU, one compiled function per configuration.

A batch is one call of a jitted function: `lax.scan` over `nstep` of `vmap(mjx.step)` over
`nbatch` trajectories. The function takes the model, the initial states, the controls and a
seed as arguments, so it is traced and compiled once per configuration (and device) and reused
by every batch and every iterator of the dataset. Random controls are drawn inside it with
`jax.random`; initial states are drawn on the host (they are small) and transferred.

Each trajectory starts as `mujoco.rollout` starts it: `mj_resetData` defaults (zero inputs,
mocap bodies at their model poses, `eq_active0`, zero warmstart) with the `mjSTATE_FULLPHYSICS`
part from the initial state. Before every step the `control_spec` components are set from the
control row, as `mj_setState` does. MJX never checks for instability, so every step is checked
here as MuJoCo checks it (|qpos|, |qvel|, |qacc| within mjMAXVAL, all finite) plus the sensors;
a trajectory that fails is flagged in `diverged` and, as in MuJoCo, continues from the state
`mj_resetData` leaves: no NaN is delivered, and the others are bit-identical to a run without it.

A model list or a variant pool is one mjx.Model batched only where the models differ; a
randomization spec is drawn and applied inside the batch function (`mjx_randomize`). With
`continue_episodes` a batch hands the next only what a step reads of the previous one (physics
state, solver warmstart) and the randomized values: the next batch resets its rows and sets
these back, which is exact and keeps checkpoints small.

`produce` only dispatches (JAX runs asynchronously); `deliver` waits for the results and hands
every output to torch through DLPack: the delivered tensors are the JAX buffers, on the torch
device of the JAX device (`cuda:k` for JAX GPU k). They are fresh buffers for every batch, but
shared with JAX: treat them as read-only (clone before editing in place). In a (spawned)
DataLoader worker, GPU tensors are copied once into torch's memory, the only GPU memory torch
can pass to the main process; `num_workers=0` needs no worker and no copy.

Process-wide JAX settings: unless told otherwise, JAX does not preallocate GPU memory (so that
a torch model can train on the same GPU) and compilations are kept in a persistent cache.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import sys
import threading
import time
import warnings
import weakref
from collections.abc import Callable
from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import torch
from jax._src import xla_bridge
from mujoco import mjx

from simloader import handoff, layout, resume, sharding
from simloader import randomize as dr
from simloader.backends import mjx_randomize
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig

S = mujoco.mjtState
# The mjSTATE_FULLPHYSICS components MJX simulates. The others must be empty (checked at
# construction), so this spec's layout is FULLPHYSICS's, column for column.
PHYSICS = int(S.mjSTATE_TIME | S.mjSTATE_QPOS | S.mjSTATE_QVEL | S.mjSTATE_ACT)
_UNSIMULATED = (
    (S.mjSTATE_HISTORY, "actuator and sensor delays", "nhistory"),
    (S.mjSTATE_PLUGIN, "plugins with state", "npluginstate"),
    (S.mjSTATE_PLASTIC, "plasticity", "nplastic"),
)
# The user inputs mj_resetData takes from the model (all others it zeroes).
_MODEL_INPUTS = int(S.mjSTATE_EQ_ACTIVE | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT)
# mjMAXVAL: beyond it MuJoCo's own checks call qpos, qvel and qacc unstable.
_MAXVAL = 1e10

OPTIONS = ("compilation_cache", "memory_fraction")
_PREALLOCATE = "XLA_PYTHON_CLIENT_PREALLOCATE"
_FRACTION = "XLA_CLIENT_MEM_FRACTION"
_FRACTION_DEPRECATED = "XLA_PYTHON_CLIENT_MEM_FRACTION"  # jaxlib rejects both being set


def check_options(config: SimConfig, options: dict[str, Any]) -> dict[str, Any]:
    """Validates the mjx options and the model(s), in the constructing process.

    Args:
      config: the validated dataset configuration.
      options: keyword options of `SimDataset` beyond its own:
        compilation_cache: directory of JAX's persistent compilation cache; None (default):
          JAX's configured one, else `~/.cache/simloader/jax`; False: leave JAX's setting.
        memory_fraction: fraction of GPU memory JAX preallocates; None (default): none, JAX
          allocates as it goes (effective only if JAX has not started yet).

    Returns:
      The options for `MjxBackend`, defaults resolved.

    Raises:
      TypeError: an unknown option or a value of the wrong type.
      ValueError: a bad option value, a model MJX cannot simulate, models or variants that
        differ in what MJX compiles in, or a parameter MJX cannot randomize (`mjx_randomize`).
    """
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {unknown} for "
                        f"backend='mjx' (its options are {list(OPTIONS)})")
    cache = _cache_dir(options.get("compilation_cache"))
    fraction = configure_memory(options.get("memory_fraction"))
    _configure_cache(cache)
    mx, _ = _put_models(config, _jax_device(config.device))
    if config.randomization is not None:
        mjx_randomize.check(config.model, mx, config.randomization)
    return {"compilation_cache": cache, "memory_fraction": fraction}


def configure_memory(memory_fraction: Any) -> Optional[float]:
    """Sets how JAX takes GPU memory; effective only before JAX starts its backends.

    Args:
      memory_fraction: None: no preallocation; a number in (0, 1]: preallocate that fraction.

    Returns:
      The validated fraction.

    Raises:
      TypeError, ValueError: `memory_fraction` is not None or a number in (0, 1].
    """
    if memory_fraction is not None and (isinstance(memory_fraction, bool) or not isinstance(
            memory_fraction, (int, float, np.floating, np.integer))):
        raise TypeError(f"memory_fraction: expected None or a number in (0, 1], got "
                        f"{type(memory_fraction).__name__} {memory_fraction!r}")
    if memory_fraction is not None and not 0 < memory_fraction <= 1:
        raise ValueError(f"memory_fraction: expected None or a number in (0, 1], got "
                         f"{memory_fraction}")
    fraction = None if memory_fraction is None else float(memory_fraction)
    if not xla_bridge.backends_are_initialized():  # JAX has no public "started" query
        if fraction is None:
            os.environ.setdefault(_PREALLOCATE, "false")  # a user's explicit choice stands
        else:
            os.environ[_PREALLOCATE] = "true"
            os.environ.pop(_FRACTION_DEPRECATED, None)
            os.environ[_FRACTION] = str(fraction)
        return fraction
    if not any(d.platform == "gpu" for d in jax.devices()):
        return fraction
    # the same test jaxlib applies when it creates the GPU client
    preallocating = os.environ.get(_PREALLOCATE, "true") not in ("false", "False", "0")
    current = os.environ.get(_FRACTION) or os.environ.get(_FRACTION_DEPRECATED)
    if fraction is None and preallocating:
        warnings.warn(
            "simloader: JAX was started before simloader could turn off its GPU memory "
            "preallocation, so JAX may hold 75% of the GPU and leave little to torch. Set "
            f"{_PREALLOCATE}=false before JAX starts (or create the SimDataset first).",
            RuntimeWarning, stacklevel=3)
    elif fraction is not None and current != str(fraction):
        warnings.warn(
            f"simloader: memory_fraction={fraction} has no effect: JAX was already started "
            f"(with {_FRACTION}={current}). Create the SimDataset before anything starts JAX, "
            f"or set {_FRACTION} yourself.", RuntimeWarning, stacklevel=3)
    return fraction


def _cache_dir(value: Any) -> Any:
    if value is False:
        return False
    if value is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
        return jax.config.jax_compilation_cache_dir or os.path.join(base, "simloader", "jax")
    if isinstance(value, (str, os.PathLike)):
        return os.fspath(value)
    raise TypeError(f"compilation_cache: expected a directory path, None (default cache) or "
                    f"False (leave JAX's setting), got {type(value).__name__} {value!r}")


def _configure_cache(path: Any) -> None:
    # JAX reads these at its first compilation in the process; later changes are ignored
    if path is not False:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def _refuse_forked_worker() -> None:
    """JAX is multithreaded and deadlocks in a forked child (its parent already ran JAX)."""
    if torch.utils.data.get_worker_info() is None:
        return
    # a DataLoader started with a context uses its Process class, which names its start
    # method; a plain Process uses the global one, which a forked child inherits
    method = (getattr(multiprocessing.current_process(), "_start_method", None)
              or multiprocessing.get_start_method())
    if method == "fork":
        raise RuntimeError(
            "backend='mjx' cannot run in a forked DataLoader worker: JAX is multithreaded and "
            "deadlocks after fork. Use num_workers=0 (an MJX batch already runs in parallel on "
            "the device) or DataLoader(..., multiprocessing_context='spawn').")


def _jax_device(target: Optional[torch.device]) -> jax.Device:
    """Where to simulate: JAX GPU k for a `cuda:k` target (no copy at delivery), else JAX's
    GPU of this local rank (torchrun's LOCAL_RANK), else JAX's default device."""
    gpus = [d for d in jax.local_devices() if d.platform == "gpu"]
    if not gpus:
        return jax.local_devices()[0]
    if target is not None and target.type == "cuda":
        index = target.index if target.index is not None else torch.cuda.current_device()
    else:
        index = int(os.environ.get("LOCAL_RANK", "0"))
    # by CUDA ordinal, not by position (JAX may see fewer GPUs than torch)
    for gpu in gpus:
        if gpu.local_hardware_id == index:
            return gpu
    if target is not None and target.type == "cuda":
        raise ValueError(f"device: {target} requested but JAX sees only the GPU(s) "
                         f"{[g.local_hardware_id for g in gpus]}")
    return gpus[index % len(gpus)]


def _put_models(config: SimConfig, device: jax.Device) -> tuple[mjx.Model, Any]:
    """The model, or the model list or variant pool as one mjx.Model batched only where the
    models differ.

    Returns:
      (model, in_axes): `in_axes` is the model's `vmap` axes, 0 on the fields that differ
      across the list and None elsewhere (None altogether for a single model).

    Raises:
      ValueError: MJX cannot simulate a model, or the models differ in a field MJX compiles in.
    """
    models = _pool(config)
    names = (["model"] if len(models) == 1 else
             [f"randomize[{i}]" for i in range(len(models))] if config.models is not None else
             [f"randomize: variant[{i}]" for i in range(len(models))])
    # a list is compared and stacked on the host, then moved at once
    host = device if len(models) == 1 else jax.local_devices(backend="cpu")[0]
    puts = []
    for name, model in zip(names, models):
        for bit, what, size in _UNSIMULATED:
            if mujoco.mj_stateSize(model, int(bit)):
                raise ValueError(f"{name}: MJX does not support {what} ({size}="
                                 f"{mujoco.mj_stateSize(model, int(bit))}); use "
                                 f"backend='rollout'")
        try:
            puts.append(mjx.put_model(model, device=host, impl="jax"))
        except NotImplementedError as e:
            raise ValueError(f"{name}: MJX does not support a feature of this model: {e}; use "
                             f"backend='rollout'") from None
    if len(puts) == 1:
        return puts[0], None
    if models[0].nhfield == 0:
        # MJX keeps a static copy of geom_rbound, read only to size the patch of a height field
        # a geom collides with: without height fields it would make models differing in a geom
        # size (variants) differ in a compiled-in field for nothing
        puts = [put.replace(_impl=put._impl.replace(
            geom_rbound_hfield=np.zeros_like(put._impl.geom_rbound_hfield))) for put in puts]
    leaves, treedef = jax.tree_util.tree_flatten(puts[0])
    columns = [leaves]
    for name, put in zip(names[1:], puts[1:]):
        other, other_def = jax.tree_util.tree_flatten(put)
        if other_def != treedef:
            raise ValueError(
                f"{name}: {_static_difference(puts[0], put, 'model')} differs from "
                f"{names[0]}, but MJX compiles it into the simulation; only numeric "
                f"parameters may differ across the models")
        columns.append(other)
    batched, axes = [], []
    for column in zip(*columns):
        same = all(np.array_equal(column[0], leaf) for leaf in column[1:])
        batched.append(column[0] if same else jnp.stack(column))
        axes.append(None if same else 0)
    return jax.device_put(treedef.unflatten(batched), device), treedef.unflatten(axes)


def _pool(config: SimConfig) -> tuple[mujoco.MjModel, ...]:
    """The models trajectories pick from: the model list, the variant pool, or the model."""
    return config.models or config.variants or (config.model,)


def _pooled(config: SimConfig) -> bool:
    """Whether trajectories pick their model from a pool (per-model inputs, one row each)."""
    return config.models is not None or config.variants is not None


def _static_difference(a: Any, b: Any, path: str) -> str:
    """The first non-array field (compiled in) where two mjx.Models differ, as a path."""
    if isinstance(a, jax.Array):
        return ""
    if dataclasses.is_dataclass(a):
        parts = [(f".{f.name}", getattr(a, f.name), getattr(b, f.name))
                 for f in dataclasses.fields(a)]
    elif isinstance(a, (tuple, list)) and len(a) == len(b):
        parts = [(f"[{i}]", x, y) for i, (x, y) in enumerate(zip(a, b))]
    else:
        return "" if np.array_equal(a, b) else path
    for name, x, y in parts:
        found = _static_difference(x, y, path + name)
        if found:
            return found
    return ""


def _rows(mask: jax.Array, x: jax.Array) -> jax.Array:
    """A (nbatch,) mask shaped to select rows of the batched array `x`."""
    return mask.reshape((-1,) + (1,) * (x.ndim - 1))


def _restarted(restart: jax.Array, fresh: jax.Array, kept: jax.Array) -> jax.Array:
    """Per row: `fresh` where the (nbatch,) `restart` is set, else `kept`."""
    return jnp.where(_rows(restart, fresh), fresh, kept)


def _key(seed: jax.Array) -> jax.Array:
    """A JAX key from a (2,) uint32 row of a batch's SeedSequence."""
    return jax.random.fold_in(jax.random.key(seed[0]), seed[1])


def _simulator(c: SimConfig, model_axes: Any, pool_axes: Any,
               randomizer: Optional[mjx_randomize.Randomizer], dtype: np.dtype) -> Callable:
    """The pure function that simulates one batch of configuration `c`.

    The returned `simulate(model, data0, inputs0, x0, control, seeds, variant, carry,
    restart)` takes:
      model: the mjx.Model; a model list or variant pool is batched along `pool_axes`.
      data0: one trajectory's mjx.Data as `make_data` leaves it.
      inputs0: `_MODEL_INPUTS` rows as mj_resetData leaves them, (ninputs,) or per model of
        the pool (npool, ninputs).
      x0: (nbatch, nstate) initial states, or per variant (nvariant, nstate) when they come
        from the model.
      control: the fixed controls (nbatch, nstep, ncontrol), or the default rows
        ([nbatch or 1 or nvariant], ncontrol) of undriven columns.
      seeds: (2, 2) uint32, this batch's CONTROL and RANDOMIZE seeds.
      variant: with variants, (nbatch,) int32 each trajectory's variant (drawn on the host as
        the rollout backend draws it); None otherwise.
      carry, restart: with `continue_episodes`, what the previous batch left ({"state":
        (nbatch, nstate) after its last step, "qacc_warmstart": (nbatch, nv), "params": the
        randomized values and variants}) and the (nbatch,) bool rows to restart from `x0`
        with fresh values instead; None otherwise.

    It returns (outputs, carry): the batch's dict of arrays and, with `continue_episodes`,
    the carry for the next batch.
    """
    # only plain values are captured: the program that holds this function is cached per
    # configuration and must not keep the configuration alive
    nbatch, nstep, control_spec, drivers = c.nbatch, c.nstep, c.control_spec, c.control.drivers
    given = c.control.fixed is not None or bool(drivers)  # control=None leaves inputs alone
    shape = (nbatch, nstep, c.ncontrol)
    per_model, continuing = _pooled(c), c.continue_episodes
    variants, fixed_control = c.variants is not None, c.control.fixed is not None
    x0_per_variant = variants and c.initial.from_model

    def reset(m, d0, inputs0, x0):
        d = mjx.set_state(m, d0, inputs0, _MODEL_INPUTS)
        return mjx.set_state(m, d, x0, PHYSICS)

    def step(m, d, u):
        if given:
            d = mjx.set_state(m, d, u, control_spec)
        return mjx.step(m, d)

    def restart_unstable(m, d):
        """Flags the trajectories (of batched `d`) that went unstable, and restarts them as
        mj_resetData leaves them, as MuJoCo does: their NaNs are never delivered, and the
        solver loops of the whole batch, which run until every trajectory converges, do not
        keep iterating on them. Done on the batch, not inside `vmap`: fewer, fused kernels."""
        # NaN compares False, so `<=` catches NaN, Inf and huge values at once
        stable = (jnp.all(jnp.abs(physics(m, d)) <= _MAXVAL, axis=-1)
                  & jnp.all(jnp.abs(d.qacc) <= _MAXVAL, axis=-1)
                  & jnp.all(jnp.isfinite(d.sensordata), axis=-1))

        def keep(x, reset):
            return jnp.where(_rows(stable, x), x, reset)

        # a step reads only these of the previous one (besides the inputs, which are not
        # simulated); mj_resetData zeroes all but qpos
        d = d.replace(time=keep(d.time, 0.0), qpos=keep(d.qpos, m.qpos0),
                      qvel=keep(d.qvel, 0.0), act=keep(d.act, 0.0),
                      qacc_warmstart=keep(d.qacc_warmstart, 0.0),
                      sensordata=keep(d.sensordata, 0.0))
        return d, ~stable

    def physics(m, d):
        return jax.vmap(lambda m, d: mjx.get_state(m, d, PHYSICS), (model_axes, 0))(m, d)

    def draw(defaults, seed):
        control = jnp.broadcast_to(defaults[:, None, :], shape)
        for driver, k in zip(drivers, jax.random.split(_key(seed), len(drivers))):
            params = {name: jnp.asarray(v, dtype) for name, v in driver.params.items()}
            sample = driver.generator.sample_jax(k, params, (*shape[:2], len(driver.columns)))
            control = control.at[..., driver.columns].set(sample.astype(dtype))
        return control

    def simulate(m, d0, inputs0, x0, control, seeds, variant, carry, restart):
        params = {}  # the values each trajectory runs with, delivered in `params`
        if variants:
            if continuing:
                variant = _restarted(restart, variant, carry["params"]["variant"])
            m = mjx_randomize.gather(m, pool_axes, variant)
            inputs0 = inputs0[variant]
            control = control if fixed_control else control[variant]
            x0 = x0[variant] if x0_per_variant else x0
            params["variant"] = variant
        if randomizer is not None:
            values = randomizer.plan.sample_jax(_key(seeds[1]), nbatch, dtype)
            if continuing:
                values = {k: _restarted(restart, v, carry["params"][k])
                          for k, v in values.items()}
            m = randomizer(m, d0, values, nbatch)
            params.update(values)
        if continuing:
            # a step reads no more of the previous one than its physics state and the solver
            # warmstart (inputs are set before every step): carrying only these restores the
            # trajectory exactly, and makes a small checkpoint
            x0 = _restarted(restart, x0, carry["state"])
        data = jax.vmap(reset, (model_axes, None, 0 if per_model else None, 0))(
            m, d0, inputs0, x0)
        if continuing:
            data = data.replace(qacc_warmstart=_restarted(
                restart, jnp.zeros_like(data.qacc_warmstart), carry["qacc_warmstart"]))
        initial = physics(m, data)
        if drivers:
            control = draw(control, seeds[0])
        elif not given:
            control = jnp.broadcast_to(control[:, None, :], shape)

        def body(loop, u):
            d, diverged = loop
            d = jax.vmap(step, (model_axes, 0, 0 if given else None))(m, d, u)
            d, unstable = restart_unstable(m, d)
            return (d, diverged | unstable), (physics(m, d), d.sensordata)

        xs = jnp.swapaxes(control, 0, 1) if given else None
        (data, diverged), (state, sensordata) = jax.lax.scan(
            body, (data, jnp.zeros(nbatch, bool)), xs, length=nstep)
        outputs = {
            "state": jnp.swapaxes(state, 0, 1),
            "sensordata": jnp.swapaxes(sensordata, 0, 1),
            "control": control,
            "initial_state": initial,
            "diverged": diverged,
        }
        if params:
            outputs["params"] = params
        if not continuing:
            return outputs, None
        return outputs, {"state": state[-1], "qacc_warmstart": data.qacc_warmstart,
                         "params": params}

    return simulate


class _Program:
    """A configuration's simulation on one device: the model and constant inputs on the
    device and the compiled batch function, shared by every iterator of the dataset."""

    def __init__(self, config: SimConfig, device: jax.Device):
        c = config
        self.model, pool_axes = _put_models(c, device)
        self.data0 = mjx.make_data(c.model, device=device, impl="jax")
        self.dtype = self.data0.qpos.dtype  # float32 unless JAX runs with x64
        # per model of the pool (variants too): the inputs and states mj_resetData leaves
        pool = _pool(c)
        inputs0 = layout.reset_rows(pool, _MODEL_INPUTS).astype(self.dtype)
        self.inputs0 = jax.device_put(inputs0 if _pooled(c) else inputs0[0], device)
        control_defaults, variant_states = (
            (c.control.default_rows, None) if c.variants is None else c.variant_defaults())
        constant = c.control.fixed if c.control.fixed is not None else control_defaults
        self.control = jax.device_put(constant.astype(self.dtype), device)
        # fixed initial states go to the device once; generated ones with every batch
        if c.initial.generator is not None:
            x0 = None
        else:
            x0 = variant_states if variant_states is not None else c.initial.fixed
        self.x0 = None if x0 is None else jax.device_put(x0.astype(self.dtype), device)
        self.randomizer = (None if c.randomization is None else mjx_randomize.Randomizer(
            c.model, c.randomization, pool_axes, self.model))
        model_axes = pool_axes if self.randomizer is None else self.randomizer.axes
        # `params` keys in the order of the spec, as the rollout backend gives them (JAX
        # returns dicts sorted)
        self.param_keys = (("variant",) if c.variants is not None else
                           () if c.randomization is None else
                           tuple(r.param.key for r in c.randomization.resolved))
        self.jitted = jax.jit(_simulator(c, model_axes, pool_axes, self.randomizer, self.dtype))
        self.compiled: Optional[Callable] = None
        self.lock = threading.Lock()

    def initial_carry(self, c: SimConfig) -> Any:
        """A carry of the right shapes for the first batch, which restarts every row."""
        zeros = lambda *shape: np.zeros((c.nbatch, *shape), self.dtype)  # noqa: E731
        params = ({} if self.randomizer is None else
                  {r.param.key: zeros(len(r.elements)) for r in self.randomizer.plan.resolved})
        if c.variants is not None:
            params["variant"] = np.zeros(c.nbatch, np.int32)
        return {"state": zeros(c.nstate), "qacc_warmstart": zeros(c.model.nv), "params": params}

    def compile(self, args: tuple, stats: Stats) -> Callable:
        """The compiled batch function, compiled (or loaded from JAX's cache) on first use."""
        with self.lock:
            if self.compiled is None:
                start = time.perf_counter()
                # true float32 dot products: on GPUs JAX defaults to TF32, whose 10-bit
                # mantissa puts 4e-4 errors into one step of the humanoid's velocities
                with jax.default_matmul_precision("float32"):
                    lowered = self.jitted.lower(*args)
                self.compiled = lowered.compile()
                stats.add(compile_s=time.perf_counter() - start, compiles=1)
            return self.compiled


# programs by configuration and device; each epoch's iterator reuses its dataset's program,
# which goes away with the dataset's configuration
_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


@dataclasses.dataclass
class _Produced:
    outputs: dict[str, Any]  # arrays (and the `params` dict), dispatched, maybe not ready yet
    dispatched: float  # time.perf_counter() at dispatch
    carry: Any = None  # continue_episodes: what the next batch continues from


class MjxBackend(Backend):
    """`backend="mjx"`.

    Args:
      config, shard, stats: as every backend.
      compilation_cache, memory_fraction: as resolved by `check_options`.

    Raises:
      RuntimeError: in a forked DataLoader worker, where JAX would deadlock.
    """

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats, *,
                 compilation_cache: Any, memory_fraction: Optional[float]):
        _refuse_forked_worker()
        super().__init__(config, shard, stats)
        # again here: a spawned worker inherits the environment but not JAX's configuration
        configure_memory(memory_fraction)
        _configure_cache(compilation_cache)
        device = _jax_device(config.device)
        self.program = _PROGRAMS.setdefault(config, {}).get(device)
        if self.program is None:
            self.program = _PROGRAMS[config][device] = _Program(config, device)
        self.device = device
        self.carry: Any = None
        self.restart: Any = None
        if config.continue_episodes:
            # the first batch starts every row from x0, so any carry of the right shapes will do
            self.carry = jax.device_put(self.program.initial_carry(config), device)
            self.restart = np.ones(config.nbatch, dtype=bool)
        self.last_ready = 0.0
        self.last_dispatched: Any = None  # outputs of the newest dispatched batch
        self.in_worker = torch.utils.data.get_worker_info() is not None

    def produce(self, index: int) -> _Produced:
        c, p = self.config, self.program
        x0 = p.x0 if p.x0 is not None else c.initial.sample(
            self.seed(index, sharding.INITIAL), c.nbatch).astype(p.dtype)
        randomize_seed = self.seed(index, sharding.RANDOMIZE)
        seeds = np.stack([self.seed(index, sharding.CONTROL).generate_state(2, np.uint32),
                          randomize_seed.generate_state(2, np.uint32)])
        variant = None if c.variants is None else dr.draw_variants(
            randomize_seed, len(c.variants), c.nbatch).astype(np.int32)
        args = (p.model, p.data0, p.inputs0, x0, p.control, seeds, variant, self.carry,
                self.restart)
        simulate = p.compile(args, self.stats)
        dispatched = time.perf_counter()
        outputs, carry = simulate(*args)
        self.last_dispatched = outputs
        if c.continue_episodes:
            # diverged rows restart in the next batch, decided on the device without waiting
            self.carry, self.restart = carry, outputs["diverged"]
        return _Produced(outputs, dispatched, carry)

    def deliver(self, produced: _Produced) -> dict[str, torch.Tensor]:
        c = self.config
        # waiting here also orders the hand-off before any torch stream reads the buffers
        outputs = jax.block_until_ready(produced.outputs)
        ready = time.perf_counter()
        # the device runs batches in order: this one started at its dispatch or when the
        # previous one was ready, whichever is later (when the consumer is slower than the
        # simulation, results wait and this over-counts)
        self.stats.add(simulate_s=ready - max(produced.dispatched, self.last_ready),
                       batches=1, steps=c.nbatch * c.nstep,
                       diverged=int(np.count_nonzero(outputs["diverged"])))
        self.last_ready = ready
        batch = {key: self._tensor(array, None if key == "diverged" else c.dtype)
                 for key, array in outputs.items() if key != "params"}
        if "params" in outputs:
            # variant indices as the rollout backend gives them (JAX has no int64 without x64)
            batch["params"] = {key: self._tensor(outputs["params"][key],
                                                 torch.int64 if key == "variant" else c.dtype)
                               for key in self.program.param_keys}
        return batch

    def _tensor(self, array: jax.Array, dtype: Optional[torch.dtype]) -> torch.Tensor:
        tensor = handoff.to_target(handoff.from_jax(array), self.config.device, dtype)
        if (self.in_worker and tensor.is_cuda
                and tensor.data_ptr() == array.unsafe_buffer_pointer()):
            # CUDA IPC, which carries a worker's tensors to the main process, shares only
            # torch's own allocations, not JAX's: a worker hands over a copy
            tensor = tensor.clone()
        return tensor

    def checkpoint(self, produced: _Produced) -> Optional[dict[str, Any]]:
        if not self.config.continue_episodes:
            return None
        carry = produced.carry
        return {"state": resume.encode_array(np.asarray(carry["state"])),
                "qacc_warmstart": resume.encode_array(np.asarray(carry["qacc_warmstart"])),
                "restart": resume.encode_array(np.asarray(produced.outputs["diverged"])),
                "params": {k: resume.encode_array(np.asarray(v))
                           for k, v in carry["params"].items()}}

    def restore(self, trajectories: dict[str, Any]) -> None:
        carry = {"state": resume.decode_array(trajectories["state"]),
                 "qacc_warmstart": resume.decode_array(trajectories["qacc_warmstart"]),
                 "params": {k: resume.decode_array(v)
                            for k, v in trajectories["params"].items()}}
        self.carry = jax.device_put(carry, self.device)
        self.restart = resume.decode_array(trajectories["restart"])

    def close(self, _finalizing: Callable[[], bool] = sys.is_finalizing) -> None:
        # (`_finalizing` is bound at definition: at exit this module's globals may be gone)
        # batches already dispatched but never delivered would otherwise keep the GPU busy
        # (and their memory held) after the iterator is gone; the device runs them in order,
        # so waiting for the last one waits for all. Not at interpreter exit (an iterator left
        # open): the process and its device work end anyway, and modules are being torn down
        if self.last_dispatched is not None and not _finalizing():
            jax.block_until_ready(self.last_dispatched)
        # the carry is this iterator's; the program stays for the dataset's next iterator
        self.carry = self.restart = self.last_dispatched = None
