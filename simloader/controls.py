"""Control generators: fresh open-loop control sequences for every batch, on either backend.

A generator drives one `control_spec` component (`ctrl`, `qfrc_applied`, `xfrc_applied`,
`eq_active`, `mocap_pos`, `mocap_quat`, `userdata`), optionally only some of its objects,
addressed by name with `on=`::

    control = simloader.controls.Uniform()                       # actuator controls
    control = {"ctrl": controls.Uniform(),
               "xfrc_applied": controls.Normal(std=20.0, on="torso")}  # + a force on one body

Columns no generator drives hold what `mj_resetData` leaves (zero forces and controls, mocap
bodies at their model poses, equalities at `eq_active0`). Each generator draws with NumPy on
the CPU backend and with `jax.random` inside the jitted step on the MJX backend: the numbers
differ between backends, the distributions do not.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any, Optional, Union

import mujoco
import numpy as np

from simloader import draws, layout
from simloader.rules import MAXVAL

Names = Optional[Union[str, Sequence[str]]]


class Generator(abc.ABC):
    """Base class of control generators.

    Subclasses are frozen dataclasses with an `on` field and implement `params` (per-column
    parameters, computed once on the host) and `sample` (one draw of shape
    `(nbatch, nstep, ncolumns)` for the columns they drive), written once over a
    `simloader.draws` array library: NumPy for the CPU engine, JAX for MJX, torch for Warp.
    """

    on: Names
    draws: int = 1  # random draws per sample (JAX splits its key into as many)

    @abc.abstractmethod
    def params(self, model: mujoco.MjModel, component: layout.Component,
               columns: np.ndarray) -> dict[str, np.ndarray]:
        """Per-column parameters for the driven `columns` (indices within `component`)."""

    def check_shape(self, shape: tuple[int, int, int]) -> None:
        """Validates the draw shape (nbatch, nstep, ncolumns) at construction (ValueError)."""

    @abc.abstractmethod
    def sample(self, d: Any, params: dict[str, Any], shape: tuple[int, int, int]) -> Any:
        """A draw of `shape` = (nbatch, nstep, ncolumns) with `d` (a `simloader.draws`
        library and its random state), in the dtype (and on the device) of `params`, arrays
        of that library: float64 NumPy on the host, JAX in the jitted batch, torch on the
        Warp engine's GPU."""


def _per_column(value: Any, component: layout.Component, columns: np.ndarray,
                what: str) -> np.ndarray:
    """Broadcasts a scalar, a per-object-width vector, or a per-column vector to the columns."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return np.full(len(columns), float(arr))
    if arr.shape == (len(columns),):
        return arr.copy()
    if arr.shape == (component.width,) and len(columns) % component.width == 0:
        return np.tile(arr, len(columns) // component.width)
    raise ValueError(
        f"{what}: expected a scalar, {component.width} values (one object of "
        f"{component.name}) or {len(columns)} values (one per driven column), got shape "
        f"{arr.shape}")


def _ctrl_bounds(model: mujoco.MjModel, component: layout.Component, columns: np.ndarray,
                 otherwise: float) -> tuple[np.ndarray, np.ndarray]:
    """Each driven column's bounds: `ctrlrange` for `ctrl` columns of limited actuators, else
    [-otherwise, otherwise]."""
    low, high = np.full(len(columns), -otherwise), np.full(len(columns), otherwise)
    if component.name == "ctrl":
        limited = model.actuator_ctrllimited[columns].astype(bool)
        low[limited] = model.actuator_ctrlrange[columns[limited], 0]
        high[limited] = model.actuator_ctrlrange[columns[limited], 1]
    return low, high


@dataclasses.dataclass(frozen=True)
class Uniform(Generator):
    """Independent uniform draws in `[low, high)` at every step.

    Args:
      low, high: bounds, a scalar or one value per column; `None` gives each actuator's
        `ctrlrange` for `ctrl` (`[-1, 1]` for unlimited actuators) and -1 / 1 elsewhere.
      on: the objects to drive (actuator, body, joint dof, mocap body or equality names);
        `None` drives the whole component.
    """

    low: Any = None
    high: Any = None
    on: Names = None

    def params(self, model, component, columns):
        low, high = _ctrl_bounds(model, component, columns, 1.0)  # natural range
        if self.low is not None:
            low = _per_column(self.low, component, columns, "Uniform.low")
        if self.high is not None:
            high = _per_column(self.high, component, columns, "Uniform.high")
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low <= high)):
            raise ValueError(f"Uniform: expected finite low <= high, got low={low}, high={high}")
        return {"low": low, "high": high}

    def sample(self, d, params, shape):
        return d.uniform(params["low"], params["high"], shape)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Normal(Generator):
    """Independent Gaussian draws `mean + std * N(0, 1)` at every step.

    Keywords only (`Normal(mean=0.0, std=0.5)`): `simloader.randomize.Normal(mean, std)` takes
    the same two in this order, positionally too.

    Args:
      mean, std: a scalar or one value per column.
      clip: clip `ctrl` columns of limited actuators to their `ctrlrange` (MuJoCo clamps
        them anyway; clipping makes the recorded `control` the value that acted).
      on: the objects to drive; `None` drives the whole component.
    """

    mean: Any = 0.0
    std: Any = 1.0
    clip: bool = True
    on: Names = None

    def params(self, model, component, columns):
        return _gaussian_params(self, model, component, columns)

    def sample(self, d, params, shape):
        out = d.normal(shape, params["std"]) * params["std"] + params["mean"]
        return d.clip(out, params["low"], params["high"])


class _Given(Generator):
    """Values given before the batch (`params()["value"]`, shaped to broadcast to
    (nbatch, nstep, ncolumns)): a sample only broadcasts them."""

    draws = 0

    def sample(self, d, params, shape):
        return d.broadcast(params["value"], shape)


@dataclasses.dataclass(frozen=True)
class Constant(_Given):
    """The same value at every step of every trajectory.

    Args:
      value: a scalar, one object's columns, or one value per driven column.
      on: the objects to drive; `None` drives the whole component.
    """

    value: Any = 0.0
    on: Names = None

    def params(self, model, component, columns):
        value = _per_column(self.value, component, columns, "Constant.value")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"Constant.value: expected finite values, got {value}")
        return {"value": value}


def _gaussian_params(gen: Any, model: mujoco.MjModel, component: layout.Component,
                     columns: np.ndarray) -> dict[str, np.ndarray]:
    """Per-column std, mean and clip bounds of a generator with `mean`, `std`, `clip` fields."""
    name = type(gen).__name__
    std = _per_column(gen.std, component, columns, f"{name}.std")
    mean = _per_column(gen.mean, component, columns, f"{name}.mean")
    if not (np.all(np.isfinite(std)) and np.all(std >= 0) and np.all(np.isfinite(mean))):
        raise ValueError(f"{name}: expected finite std >= 0 and finite mean, got std={std}, "
                         f"mean={mean}")
    # clip to the ctrlrange of limited actuators when asked, else unbounded
    low, high = (_ctrl_bounds(model, component, columns, np.inf) if gen.clip
                 else (np.full(len(columns), -np.inf), np.full(len(columns), np.inf)))
    return {"std": std, "mean": mean, "low": low, "high": high}


def _positive(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            np.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True, kw_only=True)
class OrnsteinUhlenbeck(Generator):
    """Smooth noise: a stationary Ornstein-Uhlenbeck process with correlation time `tau`.

    `x[t] = mean + a (x[t-1] - mean) + std sqrt(1 - a^2) eps[t]`, `a = exp(-timestep / tau)`,
    started from the stationary distribution, so every step has standard deviation `std` and
    steps `tau` seconds apart correlate by 1/e. World models need such excitation: white noise
    at a small timestep barely moves a system. Each batch starts a fresh process. Keywords
    only, as `Normal`.

    Args:
      mean: the level the process reverts to.
      std: stationary standard deviation, a scalar or one value per column.
      tau: correlation time in seconds (simulated time, the model's timestep per step).
      clip: clip `ctrl` columns of limited actuators to their `ctrlrange`.
      on: the objects to drive; `None` drives the whole component.
    """

    mean: Any = 0.0
    std: Any = 1.0
    tau: float = 0.1
    clip: bool = True
    on: Names = None

    def params(self, model, component, columns):
        a = np.exp(-model.opt.timestep / _positive("OrnsteinUhlenbeck.tau", self.tau))
        return {**_gaussian_params(self, model, component, columns), "a": np.asarray(a)}

    def sample(self, d, params, shape):
        a, std = d.scalar(params["a"]), params["std"]
        eps = d.normal(shape, std)
        # x[0] = std eps[0]; x[t] = a x[t - 1] + std sqrt(1 - a^2) eps[t]
        x = d.concat_time(eps[:, 0] * std, eps[:, 1:] * (std * d.sqrt(1.0 - a * a)))
        return d.clip(d.linear_recurrence(x, a) + params["mean"], params["low"],
                      params["high"])


@dataclasses.dataclass(frozen=True)
class PiecewiseConstant(Generator):
    """Uniform values in `[low, high)` held for `hold` steps, then redrawn.

    Args:
      hold: steps each value is held.
      low, high: as `Uniform` (default: `ctrlrange` for `ctrl`, else [-1, 1]).
      on: the objects to drive; `None` drives the whole component.
    """

    hold: int = 10
    low: Any = None
    high: Any = None
    on: Names = None

    def params(self, model, component, columns):
        if isinstance(self.hold, bool) or not isinstance(self.hold, int) or self.hold < 1:
            raise ValueError(f"PiecewiseConstant.hold: expected an integer >= 1 (steps), got "
                             f"{self.hold!r}")
        return Uniform(self.low, self.high, self.on).params(model, component, columns)

    def sample(self, d, params, shape):
        n, t, k = shape
        held = d.uniform(params["low"], params["high"], (n, -(-t // self.hold), k))
        return d.repeat(held, self.hold, axis=1)[:, :t]


@dataclasses.dataclass(frozen=True)
class Sinusoid(Generator):
    """`offset + amplitude * sin(2 pi f t + phase)`, with a frequency drawn per trajectory and
    column uniformly in `frequency` (Hz) and a uniform random phase. With `chirp_to`, the
    frequency sweeps linearly from the drawn one to `chirp_to` (Hz) over the batch (a chirp).

    Args:
      amplitude, offset: a scalar or one value per column.
      frequency: a frequency in Hz, or a `(low, high)` range to draw from.
      chirp_to: final frequency of a linear chirp over the batch, or `None`.
      on: the objects to drive; `None` drives the whole component.
    """

    amplitude: Any = 1.0
    frequency: Any = (0.5, 2.0)
    offset: Any = 0.0
    chirp_to: Optional[float] = None
    on: Names = None

    def params(self, model, component, columns):
        low_f, high_f = (self.frequency if isinstance(self.frequency, (tuple, list))
                         else (self.frequency, self.frequency))
        for name, f in (("low", low_f), ("high", high_f)):
            _positive(f"Sinusoid.frequency ({name})", f)
        if low_f > high_f:
            raise ValueError(f"Sinusoid.frequency: expected low <= high, got {self.frequency}")
        chirp = np.nan if self.chirp_to is None else _positive("Sinusoid.chirp_to", self.chirp_to)
        return {"amplitude": _per_column(self.amplitude, component, columns, "Sinusoid.amplitude"),
                "offset": _per_column(self.offset, component, columns, "Sinusoid.offset"),
                "f_low": np.asarray(float(low_f)), "f_high": np.asarray(float(high_f)),
                "chirp_to": np.asarray(chirp), "dt": np.asarray(model.opt.timestep)}

    draws = 2  # a frequency and a phase

    def sample(self, d, params, shape):
        n, nstep, k = shape
        like = params["amplitude"]
        f0 = d.uniform(params["f_low"], params["f_high"], (n, 1, k), like)
        phase = d.uniform(0.0, 2 * np.pi, (n, 1, k), like)
        t = d.arange(nstep, f0)[None, :, None] * params["dt"]
        if self.chirp_to is None:
            angle = 2 * np.pi * f0 * t
        else:  # instantaneous frequency f0 + (f1 - f0) t / T
            duration = nstep * params["dt"]
            angle = 2 * np.pi * (f0 * t + (params["chirp_to"] - f0) * t * t / (2 * duration))
        return params["offset"] + params["amplitude"] * d.xp.sin(angle + phase)


@dataclasses.dataclass(frozen=True)
class FromArray(_Given):
    """A user array `([nbatch or 1] x [nstep or 1] x ncolumns)` for the driven columns.

    Args:
      values: the array; its last dimension is the number of driven columns.
      on: the objects to drive; `None` drives the whole component.
    """

    values: Any = None
    on: Names = None

    def params(self, model, component, columns):
        arr = np.asarray(self.values, dtype=np.float64)
        if arr.ndim != 3 or arr.shape[-1] != len(columns):
            raise ValueError(f"FromArray.values: expected [nbatch or 1] x [nstep or 1] x "
                             f"{len(columns)} (the driven columns of {component.name}), got "
                             f"shape {arr.shape}")
        return {"value": arr}

    def check_shape(self, shape):
        try:
            np.broadcast_shapes(np.shape(self.values), shape)
        except ValueError:
            raise ValueError(f"FromArray.values: shape {np.shape(self.values)} does not "
                             f"broadcast to (nbatch, nstep, ncolumns) = {shape}") from None


@dataclasses.dataclass(frozen=True)
class ColumnDriver:
    """A generator bound to its columns of the control vector, with its parameters."""

    generator: Generator
    columns: np.ndarray  # indices in the full control vector
    params: dict[str, np.ndarray]


class ControlPlan:
    """How each batch's `(nbatch, nstep, ncontrol)` control array is made.

    Built once, on the host, from the dataset's `control` argument; both backends call it.
    `fixed` is set for an explicit array, `drivers` for generators; with neither the inputs are
    left as `mj_resetData` sets them (`control=None`, as `mujoco.rollout`).
    """

    def __init__(self, model: mujoco.MjModel, control_spec: int, control: Any,
                 nbatch: int, nstep: int, models: Optional[Sequence[mujoco.MjModel]] = None):
        self.nbatch, self.nstep = nbatch, nstep
        self.components = layout.control_layout(model, control_spec)
        self.ncontrol = mujoco.mj_stateSize(model, control_spec)
        # (nbatch or 1, ncontrol): per model, since mocap poses come from each model's body_pos
        self.default_rows = layout.reset_rows(models or [model], control_spec)
        self.fixed: Optional[np.ndarray] = None
        self.drivers: tuple[ColumnDriver, ...] = ()
        if control is None:
            return
        if isinstance(control, Generator):
            if len(self.components) != 1:
                names = [c.name for c in self.components]
                raise TypeError(
                    f"control: a single generator drives one control_spec component, but "
                    f"control_spec has {len(names)} ({', '.join(names)}): pass a dict "
                    f"{{component: generator}}")
            control = {self.components[0].name: control}
        if isinstance(control, Mapping):
            self.drivers = self._bind(model, control)
            return
        self.fixed = _fixed_control(control, nbatch, nstep, model, control_spec)

    @property
    def random(self) -> bool:
        return bool(self.drivers)

    def _bind(self, model, control: Mapping) -> tuple[ColumnDriver, ...]:
        by_name = {c.name: c for c in self.components}
        drivers, taken = [], {}
        for name, gens in control.items():
            if name not in by_name:
                raise ValueError(
                    f"control: {name!r} is not a component of control_spec; its components "
                    f"are {list(by_name)} (add the bit to control_spec to drive {name!r})")
            comp = by_name[name]
            for gen in gens if isinstance(gens, (list, tuple)) else [gens]:
                if not isinstance(gen, Generator):
                    raise TypeError(f"control[{name!r}]: expected a simloader.controls "
                                    f"generator, got {type(gen).__name__}")
                cols = (np.arange(comp.size) if gen.on is None
                        else comp.object_columns(gen.on))
                for c in cols:
                    if c in taken.setdefault(name, set()):
                        raise ValueError(f"control[{name!r}]: column {c} of {name} "
                                         f"({comp.objects[c // comp.width]}) is driven twice")
                    taken[name].add(c)
                if len(cols):
                    gen.check_shape((self.nbatch, self.nstep, len(cols)))
                    drivers.append(ColumnDriver(gen, comp.start + cols,
                                          gen.params(model, comp, cols)))
        return tuple(drivers)

    def sample_numpy(self, seed: np.random.SeedSequence, out: np.ndarray,
                     defaults: Optional[np.ndarray] = None) -> None:
        """Fills `out` (nbatch, nstep, ncontrol) with one draw (each driver its own stream),
        undriven columns from `defaults` ([nbatch or 1] x ncontrol; default `default_rows`)."""
        shape = out.shape[:2]
        driven = sum(len(d.columns) for d in self.drivers)
        if driven < self.ncontrol:
            out[...] = (self.default_rows if defaults is None else defaults)[:, None, :]
        for driver, child in zip(self.drivers, seed.spawn(len(self.drivers))):
            d = draws.NumpyDraws(np.random.default_rng(child))
            draw = driver.generator.sample(d, driver.params, (*shape, len(driver.columns)))
            if len(self.drivers) == 1 and driven == self.ncontrol:
                out[...] = draw
            else:
                out[..., driver.columns] = draw

    def torch_params(self, like: Any) -> list[dict[str, Any]]:
        """Each driver's parameters as torch tensors in `like`'s dtype and on its device, for
        `sample_torch` (made once per engine)."""
        import torch
        return [{k: torch.as_tensor(v, dtype=like.dtype, device=like.device)
                 for k, v in d.params.items()} for d in self.drivers]

    def sample_torch(self, seed: np.random.SeedSequence, out: Any, params: list) -> None:
        """Fills the driven columns of `out` (nbatch, nstep, ncontrol), a torch tensor, with one
        draw on its device (each driver a generator of its own, seeded from `seed` as
        `sample_numpy` seeds its streams; the numbers differ, the distributions do not).
        Undriven columns are left as they are."""
        import torch
        for driver, p, child in zip(self.drivers, params, seed.spawn(len(self.drivers))):
            generator = torch.Generator(out.device)
            generator.manual_seed(int(child.generate_state(1, np.uint64)[0] >> 1))
            draw = driver.generator.sample(draws.TorchDraws(generator), p,
                                           (*out.shape[:2], len(driver.columns)))
            out[..., _torch_columns(driver.columns, out.device)] = draw


def _torch_columns(columns: np.ndarray, device: Any) -> Any:
    """`columns` as a torch index: a slice when they are one run (a whole component, the usual
    case: the draw is copied into a view), else an index tensor on `device` (copied there
    synchronously every batch, then an indexing kernel)."""
    import torch
    start = int(columns[0]) if len(columns) else 0
    if np.array_equal(columns, np.arange(start, start + len(columns))):
        return slice(start, start + len(columns))
    return torch.as_tensor(columns, device=device)


def sample_jax(drivers: Sequence[ColumnDriver], defaults: Any, key: Any,
               shape: tuple[int, int, int], dtype: Any) -> Any:
    """One draw of `ControlPlan.drivers` in JAX (inside a jitted function; `sample_numpy` and
    `sample_torch` are the other engines'): (nbatch, nstep, ncontrol) `defaults` rows
    ([nbatch or 1] x ncontrol) with the drivers' columns drawn, each driver from its own
    split of `key`."""
    import jax
    import jax.numpy as jnp
    control = jnp.broadcast_to(defaults[:, None, :], shape)
    for driver, k in zip(drivers, jax.random.split(key, len(drivers))):
        params = {name: jnp.asarray(v, dtype) for name, v in driver.params.items()}
        d = draws.JaxDraws(k, driver.generator.draws)
        sample = driver.generator.sample(d, params, (*shape[:2], len(driver.columns)))
        control = control.at[..., driver.columns].set(sample.astype(dtype))
    return control


def applied_bounds(models: Sequence[mujoco.MjModel], control_spec: int,
                   ctrlrange: Any = None, xp: Any = np) -> tuple[Any, Any]:
    """The range MuJoCo clamps each control column to before a step, per model.

    `ctrl` columns of actuators with `actuator_ctrllimited` (the compiled flag, in which
    `autolimits` is already resolved) get their `ctrlrange`, unless the model disables
    clamping (`mjDSBL_CLAMPCTRL`); every other column is unbounded. Backend-agnostic: with
    `ctrlrange` as JAX arrays and `xp=jax.numpy` it runs inside a jitted function.

    Args:
      models: the models (one per trajectory, one per variant, or just the model); sizes and
        flags of all but the first matter only without `ctrlrange`.
      control_spec: the mjtState bits of the control vector.
      ctrlrange: per-trajectory ranges `(n, nu, 2)` replacing the models' (a randomized
        `actuator_ctrlrange`), or None.
      xp: the array module of `ctrlrange` (numpy or jax.numpy).

    Returns:
      (low, high), each `(len(models) or n, ncontrol)`, -inf / inf where nothing clamps.
    """
    model = models[0]
    ncontrol = mujoco.mj_stateSize(model, control_spec)
    if ctrlrange is None:
        ctrlrange = np.stack([m.actuator_ctrlrange for m in models]).reshape(
            len(models), model.nu, 2)
        limited = np.stack([_clamped(m) for m in models])
    else:
        limited = _clamped(model)[None]
    n = ctrlrange.shape[0]
    if not control_spec & int(mujoco.mjtState.mjSTATE_CTRL):
        unbounded = np.full((n, ncontrol), np.inf)
        return xp.asarray(-unbounded), xp.asarray(unbounded)
    # ctrl is the first component of a control row (mjtState order)
    rest = np.full((n, ncontrol - model.nu), np.inf)
    low = xp.where(limited, ctrlrange[..., 0], -np.inf)
    high = xp.where(limited, ctrlrange[..., 1], np.inf)
    return (xp.concatenate([low, xp.asarray(-rest, low.dtype)], axis=1),
            xp.concatenate([high, xp.asarray(rest, high.dtype)], axis=1))


def _clamped(model: mujoco.MjModel) -> np.ndarray:
    """(nu,) bool: the actuators whose ctrl MuJoCo clamps to ctrlrange."""
    if model.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL):
        return np.zeros(model.nu, dtype=bool)
    return model.actuator_ctrllimited.astype(bool)


def clamp_applied(control: Any, low: Any, high: Any, xp: Any = np) -> Any:
    """The control rows as they act: `control` clamped to `[low, high]` (broadcasting, e.g.
    `(nbatch, 1, ncontrol)` bounds from `applied_bounds`), NaN kept (a bad control, flagged
    by `bad_controls`). Works on NumPy and JAX arrays (`xp`: their module)."""
    return xp.minimum(xp.maximum(control, low), high)


def bad_controls(control: Any) -> Any:
    """(nbatch,) bool: the trajectories of `control` (nbatch, ...) holding a non-finite value
    or one beyond mjMAXVAL, before clamping (MuJoCo warns only about what is still bad after
    it clamps, so `inf` on a limited actuator would pass unwarned). Works on NumPy and JAX
    arrays alike."""
    bad = ~(abs(control) <= MAXVAL)  # NaN compares False
    return bad.reshape(bad.shape[0], -1).any(axis=1)


def as_applied(control: Any, low: Any, high: Any, xp: Any = np) -> tuple[Any, Any]:
    """The rule every engine applies to control rows before they act, written once:
    `(applied, bad)`, the rows clamped as MuJoCo clamps them (`clamp_applied`) and the
    (nbatch,) trajectories flagged for a bad value before clamping (`bad_controls`). For a
    whole batch (nbatch, nstep, ncontrol) with bounds (nbatch, 1, ncontrol), or one step's
    rows (nbatch, ncontrol); NumPy, JAX and torch alike (`xp`: their module)."""
    return clamp_applied(control, low, high, xp), bad_controls(control)


def _fixed_control(control: Any, nbatch: int, nstep: int, model: mujoco.MjModel,
                   control_spec: int) -> np.ndarray:
    """Validates an explicit control array and tiles it to (nbatch, nstep, ncontrol), once."""
    ncontrol = mujoco.mj_stateSize(model, control_spec)
    if isinstance(control, (str, bytes)) or not hasattr(control, "__len__") and not hasattr(
            control, "__array__"):
        raise TypeError(
            "control: expected None, an array [nbatch or 1] x [nstep or 1] x ncontrol, a "
            f"simloader.controls generator or a dict of them, got {type(control).__name__}")
    try:
        given = np.asarray(control.numpy() if hasattr(control, "numpy") and not isinstance(
            control, np.ndarray) else control)
        if given.dtype.kind == "c":  # NumPy would drop the imaginary part with a warning
            raise TypeError(f"control: expected real numbers, got a {given.dtype} array "
                            f"(controls have no imaginary part: pass control.real if that "
                            f"is what you mean)")
        arr = given.astype(np.float64)
    except (TypeError, ValueError) as e:
        if str(e).startswith("control:"):
            raise
        raise TypeError(f"control: expected a numeric array, got {type(control).__name__} "
                        f"({e})") from e
    if arr.ndim != 3:
        raise ValueError(f"control: expected 3 dimensions [nbatch or 1] x [nstep or 1] x "
                         f"ncontrol, got shape {arr.shape}")
    if arr.shape[-1] != ncontrol:
        raise ValueError(f"control: trailing dimension must be {ncontrol} "
                         f"({ncontrol_breakdown(model, control_spec)}), got {arr.shape[-1]}")
    if arr.shape[0] not in (1, nbatch):
        raise ValueError(f"control: leading dimension must be nbatch={nbatch} or 1, got "
                         f"{arr.shape[0]}")
    if arr.shape[1] not in (1, nstep):
        raise ValueError(f"control: second dimension must be nstep={nstep} or 1, got "
                         f"{arr.shape[1]}")
    # a private copy: later edits of the caller's array must not change the stream
    return np.broadcast_to(arr, (nbatch, nstep, ncontrol)).copy()


def ncontrol_breakdown(model: mujoco.MjModel, control_spec: int) -> str:
    """`nu=21 + 6*nbody=84` style breakdown of ncontrol, for error messages."""
    words = {"ctrl": f"nu={model.nu}", "qfrc_applied": f"nv={model.nv}",
             "xfrc_applied": f"6*nbody={6 * model.nbody}",
             "eq_active": f"neq={model.neq}", "mocap_pos": f"3*nmocap={3 * model.nmocap}",
             "mocap_quat": f"4*nmocap={4 * model.nmocap}",
             "userdata": f"nuserdata={model.nuserdata}"}
    return " + ".join(words[c.name] for c in layout.control_layout(model, control_spec))
