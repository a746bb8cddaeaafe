"""One batch of a configuration as a pure JAX function, and its compilation.

A batch is one call of a jitted function: `lax.scan` over `nstep` of `vmap(step)` over `nbatch`
trajectories. The function takes the model, the initial states, the controls and a seed as
arguments, so it is traced and compiled once per configuration (and device) and reused by every
batch and every iterator of the dataset. Random controls are drawn inside it with `jax.random`;
initial states are drawn on the host (they are small) and transferred.

It resets, sets the inputs, steps and checks each trajectory the same way, in MJX's XLA
implementation (`pool.put_model`, `pool.make_data`).

Each trajectory starts as `mujoco.rollout` starts it: `mj_resetData` defaults (zero inputs,
mocap bodies at their model poses, `eq_active0`, zero warmstart) with the `mjSTATE_FULLPHYSICS`
part from the initial state. Before every step the `control_spec` components are set from the
control row, as `mj_setState` does. MJX never checks for instability, so every step is checked
here as MuJoCo checks it (|qpos|, |qvel|, |qacc| within mjMAXVAL, all finite) plus the sensors;
a trajectory that fails is flagged in `diverged` and, as in MuJoCo, continues from the state
`mj_resetData` leaves: no NaN is delivered, and the others are bit-identical to a run without it.

A model list or a variant pool is one mjx.Model batched only where the models differ; a
randomization spec is drawn and applied inside the batch function (`randomize.py`). With
`continue_episodes` a batch hands the next only what a step reads of the previous one (physics
state, solver warmstart) and the randomized values: the next batch resets its rows and sets
these back, which is exact and keeps checkpoints small.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from simloader import controls, identity, rules
from simloader.backends.base import Stats, progress_line
from simloader.backends.mjx import randomize as mjx_randomize
from simloader.backends.mjx import observe as mjx_observe
from simloader.backends.mjx import stored_program
from simloader.backends.mjx.pool import PHYSICS, make_data, pooled, put_models
from simloader.backends.mjx.runtime import mjx
from simloader.config import SimConfig

S = mujoco.mjtState
# The user inputs mj_resetData takes from the model (all others it zeroes).
MODEL_INPUTS = int(S.mjSTATE_EQ_ACTIVE | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT)


def _rows(mask: jax.Array, x: jax.Array) -> jax.Array:
    """A (nbatch,) mask shaped to select rows of the batched array `x`."""
    return mask.reshape((-1,) + (1,) * (x.ndim - 1))


def _restarted(restart: jax.Array, fresh: jax.Array, kept: jax.Array) -> jax.Array:
    """Per row: `fresh` where the (nbatch,) `restart` is set, else `kept`."""
    return jnp.where(_rows(restart, fresh), fresh, kept)


def seed_key(seed: jax.Array) -> jax.Array:
    """A JAX key from a (2,) uint32 row of a batch's SeedSequence."""
    return jax.random.fold_in(jax.random.key(seed[0]), seed[1])


class Pieces:
    """The pure pieces of one batch of configuration `c`, shared by both drivers: the open
    loop (`batch_function`: one fused scan) and the closed loop (`closed_loop.py`: one
    jitted step per call, a torch policy between calls).

    Only plain values are captured: the program that holds these functions is cached per
    configuration and must not keep the configuration alive.
    """

    def __init__(self, c: SimConfig, model_axes: Any, pool_axes: Any,
                 randomizer: Optional[mjx_randomize.Randomizer], dtype: np.dtype):
        self.model_axes, self.pool_axes = model_axes, pool_axes
        self.randomizer, self.dtype = randomizer, dtype
        self.nbatch, self.nstep, self.control_spec = c.nbatch, c.nstep, c.control_spec
        self.drivers = c.control.drivers
        self.observations, self.every, self.nframes = c.observations, c.record_every, c.nframes
        # record_kinematics="frame": the forward stage computed at each frame before it is
        # read (None: the frame as the step left it)
        self.frame_stage = c.frame_stage
        self.unchecked = [o for o in c.observations
                          if o.floating and not set(o.fields()) <= rules.RESTARTED]
        # control=None leaves inputs alone; a policy always sets them
        self.given = (c.control.fixed is not None or bool(self.drivers)
                      or getattr(c, "policy", None) is not None)
        self.shape = (c.nbatch, c.nstep, c.ncontrol)
        self.per_model, self.continuing = pooled(c), c.continue_episodes
        self.variants, self.fixed_control = c.variants is not None, c.control.fixed is not None
        self.x0_per_variant = self.variants and c.initial.from_model
        self.randomized_ctrlrange = c.randomization is not None and any(
            r.field == "actuator_ctrlrange" for r in c.randomization.resolved)
        self.ctrl_model = c.model if self.randomized_ctrlrange else None
        # with `continue_episodes`, a carry of the right shapes for the first batch (which
        # restarts every row): what `batch_function` returns beside its outputs
        zeros = lambda *shape: np.zeros((c.nbatch, *shape), dtype)  # noqa: E731
        params = ({} if randomizer is None else
                  {r.param.key: zeros(len(r.elements)) for r in randomizer.plan.resolved})
        if c.variants is not None:
            params["variant"] = np.zeros(c.nbatch, np.int32)
        # terminate=: the rules checked at every frame (None: none), and what the carry
        # holds of episodes: which rows restart at the next frame, and each episode's steps
        self.episodes = getattr(c, "terminate", None)
        episodes = ({} if self.episodes is None else
                    {"pending": np.zeros(c.nbatch, bool),
                     "episode_steps": np.zeros(c.nbatch, np.int32)})
        self.blank_carry = ({"state": zeros(c.nstate), "qacc_warmstart": zeros(c.model.nv),
                             "params": params, **episodes} if c.continue_episodes else None)

    def reset(self, m, d0, inputs0, x0):
        """One trajectory as mj_resetData leaves it, with the physics state `x0`."""
        d = mjx.set_state(m, d0, inputs0, MODEL_INPUTS)
        return mjx.set_state(m, d, x0, PHYSICS)

    def step(self, m, d, u):
        """One trajectory's step, its `control_spec` inputs set from the row `u` first."""
        if self.given:
            d = mjx.set_state(m, d, u, self.control_spec)
        return mjx.step(m, d)

    def restart_unstable(self, m, d):
        """`rules.restart_unstable` on the batched `d`: (d restarted, (nbatch,) unstable).
        Done on the batch, not inside `vmap`: fewer, fused kernels."""
        fields, unstable = rules.restart_unstable(
            {name: getattr(d, name) for name in (*rules.RESET, "qacc")}, m.qpos0, jnp)
        return d.replace(**{name: fields[name] for name in rules.RESET}), unstable

    def physics(self, m, d):
        return jax.vmap(lambda m, d: mjx.get_state(m, d, PHYSICS), (self.model_axes, 0))(m, d)

    def bounds(self, m, bounds, variant):
        """(low, high), each (nbatch or 1, ncontrol): the range MuJoCo clamps each
        trajectory's controls to (its model's ctrlrange where it clamps)."""
        if self.ctrl_model is not None:
            return controls.applied_bounds([self.ctrl_model], self.control_spec,
                                           ctrlrange=m.actuator_ctrlrange, xp=jnp)
        low, high = bounds  # per model of the pool, or one row
        if self.variants:
            low, high = low[variant], high[variant]
        return low, high

    def begin(self, m, d0, inputs0, x0, control, seeds, variant, carry, restart):
        """The batch's models, its trajectories reset (or continued), and what it delivers
        besides frames: (m, data, control, variant, params)."""
        params = {}  # the values each trajectory runs with, delivered in `params`
        if self.variants:
            if self.continuing:
                variant = _restarted(restart, variant, carry["params"]["variant"])
            m = mjx_randomize.gather(m, self.pool_axes, variant)
            inputs0 = inputs0[variant]
            control = control if self.fixed_control else control[variant]
            x0 = x0[variant] if self.x0_per_variant else x0
            params["variant"] = variant
        if self.randomizer is not None:
            values = self.randomizer.plan.sample_jax(seed_key(seeds[1]), self.nbatch, self.dtype)
            if self.continuing:
                values = {k: _restarted(restart, v, carry["params"][k])
                          for k, v in values.items()}
            m = self.randomizer(m, d0, values, self.nbatch)
            params.update(values)
        if self.continuing:
            # a step reads no more of the previous one than its physics state and the solver
            # warmstart (inputs are set before every step): carrying only these restores the
            # trajectory exactly, and makes a small checkpoint
            x0 = _restarted(restart, x0, carry["state"])
        data = jax.vmap(self.reset, (self.model_axes, None, 0 if self.per_model else None, 0))(
            m, d0, inputs0, x0)
        if self.continuing:
            data = data.replace(qacc_warmstart=_restarted(
                restart, jnp.zeros_like(data.qacc_warmstart), carry["qacc_warmstart"]))
        return m, data, control, variant, params

    def kinematics(self, m, d):
        """{name: (nbatch, ...)}: what the rules read of each trajectory's own state (its
        positions, and the kinematics mj_kinematics derives from them; not the step's,
        which are those of the state before it)."""
        E, fields = self.episodes, {}
        if "qpos" in E.reads:
            fields["qpos"] = d.qpos
        if E.kinematic:
            k = jax.vmap(mjx.kinematics, (self.model_axes, 0))(m, d)
            fields.update({name: getattr(k, name).reshape(self.nbatch, -1, 3 if name == "xpos"
                                                          else 9)
                           for name in E.reads if name != "qpos"})
        return fields

    def episode_inputs(self, x0, reset_control, variant):
        """(source, reset_control) each row's: its initial-state source's row (its variant's
        with states from the model) and the inputs a fresh frame steps with (its model's of
        the pool)."""
        source = x0[variant] if self.x0_per_variant else x0
        if reset_control.shape[0] > 1 and self.variants:  # per variant (a list: per row)
            reset_control = reset_control[variant]
        return source, reset_control

    @staticmethod
    def fresh_state(source, fresh, resets):
        """(nbatch, nstate): each row's next fresh state, its source's row, or with a
        generator (`fresh`: (nbatch, FRESH_DRAWS, nstate)) its draw `resets % FRESH_DRAWS`."""
        if fresh is None:
            return source
        return fresh[jnp.arange(fresh.shape[0]), resets % fresh.shape[1]]

    @staticmethod
    def pack_flags(terminated, truncated, first):
        """The three flags of a frame as one uint8 (bits 1, 2, 4): one scan output instead
        of three (which cost about 7% of a cart-pole step on an H200)."""
        return (terminated.astype(jnp.uint8) | truncated.astype(jnp.uint8) << 1
                | first.astype(jnp.uint8) << 2)

    def unpack_flags(self, bits, control):
        """The batch's flags ((nbatch, nframes) bool each) from `pack_flags`' bits, and its
        `control` with a fresh frame's rows NaN (they were not applied)."""
        flags = {"terminated": (bits & 1) != 0, "truncated": (bits & 2) != 0,
                 "first": (bits & 4) != 0}
        unapplied = jnp.repeat(flags["first"], self.every, axis=1)[..., None]
        return flags, jnp.where(unapplied, jnp.asarray(jnp.nan, control.dtype), control)

    def hold(self, d, rows, at):
        """The rows `rows` ((nbatch,) bool) at their fresh state `at` ((nbatch, nstate):
        time, qpos, qvel, act), with zero warmstart; the others as they are. Selects on the
        arrays themselves (fused by XLA), not through mjx.set_state."""
        nq, nv = d.qpos.shape[1], d.qvel.shape[1]
        parts = {"time": at[:, 0], "qpos": at[:, 1:1 + nq], "qvel": at[:, 1 + nq:1 + nq + nv],
                 "act": at[:, 1 + nq + nv:],
                 "qacc_warmstart": jnp.zeros_like(d.qacc_warmstart)}
        return d.replace(**{name: _restarted(rows, value.astype(getattr(d, name).dtype),
                                             getattr(d, name))
                            for name, value in parts.items()})

    def finite(self, frame):
        """(nbatch,) bool, or None with no floating observation that `restart_unstable`
        leaves unchecked (a value made only of what it restarts is finite already)."""
        return rules.finite([frame[o.key] for o in self.unchecked], jnp)


class BatchArgs(NamedTuple):
    """One batch's arguments of the batch function, by name (`batch_function` says what each
    holds). A NamedTuple: JAX flattens it, and `simulate(*args)` unpacks it."""

    model: Any
    data0: Any
    inputs0: Any
    x0: Any
    control: Any
    bounds: Any
    seeds: Any
    variant: Any
    carry: Any
    restart: Any
    fresh: Any = None
    reset_control: Any = None


def batch_function(pieces: Pieces) -> Callable:
    """The pure function that simulates one batch open loop: one scan over the batch's steps.

    The returned `simulate(model, data0, inputs0, x0, control, bounds, seeds, variant, carry,
    restart)` takes:
      model: the mjx.Model; a model list or variant pool is batched along `pool_axes`.
      data0: one trajectory's mjx.Data as `make_data` leaves it.
      inputs0: `MODEL_INPUTS` rows as mj_resetData leaves them, (ninputs,) or per model of
        the pool (npool, ninputs).
      x0: (nbatch, nstate) initial states, or per variant (nvariant, nstate) when they come
        from the model.
      control: the fixed controls (nbatch, nstep, ncontrol), or the default rows
        ([nbatch or 1 or nvariant], ncontrol) of undriven columns.
      bounds: (low, high), each ([npool or 1], ncontrol): the range MuJoCo clamps each control
        column to (`controls.applied_bounds`), per model of the pool.
      seeds: (2, 2) uint32, this batch's CONTROL and RANDOMIZE seeds.
      variant: with variants, (nbatch,) int32 each trajectory's variant (drawn on the host as
        the CPU engine draws it); None otherwise.
      carry, restart: with `continue_episodes`, what the previous batch left ({"state":
        (nbatch, nstate) after its last step, "qacc_warmstart": (nbatch, nv), "params": the
        randomized values and variants; with `terminate`, "pending" (nbatch,) bool: rows whose
        last frame met a rule, and "episode_steps" (nbatch,) int32}) and the (nbatch,) bool
        rows to restart from `x0` with fresh values instead; None otherwise.
      fresh: with `terminate` and an initial-state generator, (nbatch, FRESH_DRAWS, nstate)
        fresh states (a trajectory's e-th reset takes draw e mod FRESH_DRAWS); None: a reset
        restarts from the trajectory's `x0`.
      reset_control: with `terminate`, the `control_spec` components as mj_resetData leaves
        them, (npool or 1, ncontrol): a fresh frame's inputs (its control rows are not
        applied); None otherwise.

    It returns (outputs, carry): the batch's dict of arrays and, with `continue_episodes`,
    the carry for the next batch.

    With `terminate`, every frame's state is checked against the rules. After a frame that
    meets one, the trajectory's next frame is its fresh state: it is stepped from that state
    with the inputs mj_resetData leaves (so that what it records besides its state is the
    step's forward pass there, as the CPU engine's mj_forward), and held there (state, zero
    warmstart); its control rows are delivered as NaN.
    """
    P = pieces
    every, nframes, given, shape = P.every, P.nframes, P.given, P.shape
    E = P.episodes

    def simulate(m, d0, inputs0, x0, control, bounds, seeds, variant, carry, restart,
                 fresh=None, reset_control=None):
        m, data, control, variant, params = P.begin(m, d0, inputs0, x0, control, seeds,
                                                    variant, carry, restart)
        if E is not None:
            source, reset_control = P.episode_inputs(x0, reset_control, variant)
            resets = jnp.zeros(P.nbatch, jnp.int32)
            if P.continuing:
                # rows whose last frame met a rule start the batch at their fresh state
                held = carry["pending"] & ~restart
                steps = jnp.where(restart, 0, carry["episode_steps"])
            else:
                held = jnp.zeros(P.nbatch, bool)
                steps = jnp.zeros(P.nbatch, jnp.int32)
            at = P.fresh_state(source, fresh, resets)
            data = P.hold(data, held, at)
            episodes = (held, steps, resets + held, at)
        initial = P.physics(m, data)
        low, high = P.bounds(m, bounds, variant)
        if P.drivers:
            control = controls.sample_jax(P.drivers, control, seed_key(seeds[0]), shape, P.dtype)
        elif not given:
            control = jnp.broadcast_to(control[:, None, :], shape)
        # the control rows as MuJoCo applies them (clamped where it clamps); a bad (non-finite
        # or absurd) control flags its trajectory diverged, as on the CPU engine
        control, bad = controls.as_applied(control, low[:, None], high[:, None], jnp)
        # (nframes, record_every, nbatch, ncontrol): the rows of each frame's steps
        xs = (jnp.swapaxes(control, 0, 1).reshape(nframes, every, *control.shape[::2])
              if given else None)

        def advance(loop, u):
            d, diverged = loop[:2]
            if E is None:
                d = jax.vmap(P.step, (P.model_axes, 0, 0 if given else None))(m, d, u)
                d, unstable = P.restart_unstable(m, d)
                return (d, diverged | unstable), None
            # rows whose frame is a fresh state (set to it at the previous frame's end), and it
            held, at = loop[2:]
            if given:  # a held row's inputs stay as mj_resetData leaves them
                u = _restarted(held, jnp.broadcast_to(reset_control, u.shape), u)
            d = jax.vmap(P.step, (P.model_axes, 0, 0 if given else None))(m, d, u)
            d, unstable = P.restart_unstable(m, d)
            return (P.hold(d, held, at), diverged | unstable, held, at), None

        def record(loop, us):
            """`record_every` steps (`us`: their control rows), then one recorded frame."""
            if E is None:
                inner = loop
            else:
                d, diverged, (held, steps, resets, at) = loop
                inner = (d, diverged, held, at)
            if every == 1:
                inner, _ = advance(inner, None if us is None else us[0])
            else:
                inner, _ = jax.lax.scan(advance, inner, us, length=every)
            d, diverged = inner[:2]
            frame = mjx_observe.frame(P.observations, P.model_axes, m, d, P.frame_stage)
            finite = P.finite(frame)
            diverged = diverged if finite is None else diverged | ~finite
            if E is None:
                return (d, diverged), frame
            # the frame's flags: its state against the rules; the episode's steps
            steps = jnp.where(held, 0, steps + every)
            fields = P.kinematics(m, d)
            no = jnp.zeros(P.nbatch, bool)
            terminated = E.terminated(jnp, fields, no)
            truncated = E.truncated(jnp, steps, no)
            frame["episode/flags"] = P.pack_flags(terminated, truncated, held)
            # rows that met a rule take their fresh state now: the next frame starts there
            again = terminated | truncated
            at = _restarted(again, P.fresh_state(source, fresh, resets), at)
            d = P.hold(d, again, at)
            return (d, diverged, (again, steps, resets + again, at)), frame

        loop = (data, bad) if E is None else (data, bad, episodes)
        loop, frames = jax.lax.scan(record, loop, xs, length=nframes)
        data, diverged = loop[:2]
        outputs = {key: jnp.swapaxes(value, 0, 1) for key, value in frames.items()}
        if E is not None:
            flags, control = P.unpack_flags(outputs.pop("episode/flags"), control)
            outputs.update(flags)
        outputs.update(control=control, initial_state=initial, diverged=diverged)
        if params:
            outputs["params"] = params
        if not P.continuing:
            return outputs, None
        # what the next batch continues from (`begin`; the closed loop's `finish` alike)
        out = {"state": P.physics(m, data), "qacc_warmstart": data.qacc_warmstart,
               "params": params}
        if E is not None:
            out.update(pending=loop[2][0], episode_steps=loop[2][1])
        return outputs, out

    return simulate


@dataclasses.dataclass(frozen=True)
class Placed:
    """A configuration's models on a device (batched along `pool_axes` where a model list or
    variant pool differs) and one trajectory's data as `make_data` leaves it: what the
    construction's checks put there, and the program reuses."""

    device: jax.Device
    model: Any
    pool_axes: Any
    data0: Any

    @classmethod
    def put(cls, config: SimConfig, device: jax.Device) -> "Placed":
        model, pool_axes = put_models(config, device)
        return cls(device, model, pool_axes, make_data(config.model, device))


class Program:
    """A configuration's simulation on one device: the model and constant inputs on the
    device and the compiled batch function, shared by every iterator of the dataset.

    Args:
      config, device: what to simulate, and where.
      cache: JAX's persistent compilation cache directory, beside which the batch function is
        stored for later processes (`stored_program.py`); False: neither.
      placed: the models already on `device`, or None to put them.
    """

    def __init__(self, config: SimConfig, device: jax.Device,
                 cache: Any = False, placed: Optional[Placed] = None):
        c = config
        self.config, self.device = c, device
        placed = placed or Placed.put(c, device)
        self.model, pool_axes, self.data0 = placed.model, placed.pool_axes, placed.data0
        self.store = stored_program.store_for(cache)
        self.dtype = self.data0.qpos.dtype  # float32 unless JAX runs with x64
        # per model of the pool (variants too): the inputs and states mj_resetData leaves,
        # the range each control column is clamped to
        tables = c.model_tables(MODEL_INPUTS)
        inputs0 = tables.reset_rows.astype(self.dtype)
        self.inputs0 = jax.device_put(inputs0 if pooled(c) else inputs0[0], device)
        self.bounds = jax.device_put((tables.low.astype(self.dtype),
                                      tables.high.astype(self.dtype)), device)
        control_defaults, variant_states = tables.control_defaults, tables.variant_states
        constant = c.control.fixed if c.control.fixed is not None else control_defaults
        self.control = jax.device_put(constant.astype(self.dtype), device)
        # terminate=: a fresh frame's inputs, per model of the pool
        self.reset_control = (None if getattr(c, "terminate", None) is None else
                              jax.device_put(control_defaults.astype(self.dtype), device))
        # fixed initial states go to the device once; generated ones with every batch
        if c.initial.generator is not None:
            x0 = None
        else:
            x0 = variant_states if variant_states is not None else c.initial.fixed
        self.x0 = None if x0 is None else jax.device_put(x0.astype(self.dtype), device)
        self.randomizer = (None if c.randomization is None else mjx_randomize.Randomizer(
            c.model, c.randomization, pool_axes, self.model))
        model_axes = pool_axes if self.randomizer is None else self.randomizer.axes
        # `params` keys in the order of the spec, as the CPU engine gives them (JAX
        # returns dicts sorted)
        self.param_keys = (("variant",) if c.variants is not None else
                           () if c.randomization is None else
                           tuple(r.param.key for r in c.randomization.resolved))
        self.pieces = Pieces(c, model_axes, pool_axes, self.randomizer, self.dtype)
        self.simulate = batch_function(self.pieces)
        self.compiled: Optional[Callable] = None
        self.lock = threading.Lock()

    def compile(self, args: BatchArgs, stats: Stats) -> None:
        """Makes the batch function ready to run on `args` (as `run` takes them), once: loaded
        from the program store, or traced, compiled (JAX's persistent cache may answer) and
        stored for later processes."""
        with self.lock:
            if self.compiled is None:
                start = time.perf_counter()
                # true float32 dot products: on GPUs JAX defaults to TF32, whose 10-bit
                # mantissa puts 4e-4 errors into one step of the humanoid's velocities
                with jax.default_matmul_precision("float32"):
                    self.compiled = self._prepare(args, stats)
                stats.add(compile_s=time.perf_counter() - start, compiles=1)

    def run(self, args: BatchArgs) -> tuple[dict[str, Any], Any]:
        """Dispatches one batch (after `compile`): (outputs, carry), not yet ready."""
        return self.compiled(*jax.tree.leaves(args))

    def _prepare(self, args: BatchArgs, stats: Stats) -> Callable:
        """The compiled batch function of the flattened arguments."""
        leaves, tree = jax.tree.flatten(args)
        key = None if self.store is None else stored_program.key(self.config, self.device,
                                                                   leaves)
        exported = None if key is None else self.store.load(key)
        if exported is not None:
            stats.add(programs_loaded=1)
            return jax.jit(exported.call).lower(*leaves).compile()

        def simulate(*leaves):  # the batch function of the flattened arguments
            return self.simulate(*jax.tree.unflatten(tree, leaves))

        c = self.config
        digest = f"{self.device.platform}:{identity.model_digest(c.model)}"
        estimate = None if self.store is None else self.store.last_compile_s(digest)
        start = time.perf_counter()
        with progress_line(f"tracing and compiling the batch function ({c.nbatch} x "
                           f"{c.nstep}, MJX-JAX on {self.device.platform})",
                           estimate_s=estimate):
            if key is not None:
                exported = self._export(simulate, leaves)
            lowered = (jax.jit(simulate) if exported is None else jax.jit(exported.call)
                       ).lower(*leaves)
            stats.add(traces=1, trace_s=time.perf_counter() - start)
            compiled = lowered.compile()
        if exported is not None:
            self.store.save(key, exported)
            self.store.note_compile_s(digest, time.perf_counter() - start)
        return compiled

    def _export(self, simulate: Callable, leaves: list) -> Optional[jax.export.Exported]:
        """The batch function exported for the program store, or None (said once) where JAX
        cannot export it: it then runs as traced, and later processes trace it again."""
        try:
            return jax.export.export(jax.jit(simulate))(*leaves)
        except Exception as error:  # noqa: BLE001 (storing is an optimisation, never a failure)
            warnings.warn(f"simloader: the batch function cannot be stored for later processes "
                          f"({type(error).__name__}: {error}); each fresh process traces it "
                          f"again", RuntimeWarning, stacklevel=2)
            return None
