"""Domain randomization: model parameters drawn per trajectory, returned with the data.

One line per randomized parameter, objects addressed by name::

    from simloader import randomize as dr
    randomize = [
        dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole"),
        dr.set("geom_friction", dr.Uniform(0.3, 1.2), on="floor", index=0),
        dr.add("dof_damping", dr.Normal(0.0, 0.01, low=0.0), on="hinge"),
        dr.scale("opt.gravity", dr.Uniform(0.9, 1.1), index=2),
    ]
    ds = simloader.SimDataset(model, randomize=randomize, ...)
    batch["params"]["body_mass[pole]"]      # (nbatch, 1): the values each trajectory ran with

Values are drawn fresh for every batch (with `continue_episodes`, once per episode). `set`
replaces the model's value, `scale` multiplies it, `add` adds to it. Fields that MuJoCo derives
constants from (`mj_setConst` inputs such as body masses and inertias, and `opt.*`) have those
constants recomputed per trajectory. Each distribution is written once over a
`simloader.draws` library (`draw`): the CPU engine draws with NumPy (`RandomizationPlan.sample`)
and randomizes any floating-point field; the MJX backend draws with `jax.random` inside its
jitted function (`sample_jax`: same distributions, other numbers) and randomizes the fields
listed in `simloader.backends.mjx.randomize`.

Structural variants (geometry sizes, meshes) go through `Variants(fn, count)`: `fn(spec, rng)`
edits an `MjSpec`, compiled into a pool of `count` models sampled per trajectory
(`draw_variants`, on the host for both backends).
"""

from __future__ import annotations

import builtins
import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, Optional, Union

import mujoco
import numpy as np

from simloader import draws
from simloader.layout import did_you_mean, param_columns

Names = Optional[Union[str, Sequence[str]]]

# field prefix -> (mjtObj of the objects the rows belong to, row count attribute)
_OBJECT_KINDS = {
    "body_": (mujoco.mjtObj.mjOBJ_BODY, "nbody"),
    "geom_": (mujoco.mjtObj.mjOBJ_GEOM, "ngeom"),
    "jnt_": (mujoco.mjtObj.mjOBJ_JOINT, "njnt"),
    "dof_": (mujoco.mjtObj.mjOBJ_JOINT, "nv"),  # dofs are addressed by their joint's name
    "actuator_": (mujoco.mjtObj.mjOBJ_ACTUATOR, "nu"),
    "tendon_": (mujoco.mjtObj.mjOBJ_TENDON, "ntendon"),
    "site_": (mujoco.mjtObj.mjOBJ_SITE, "nsite"),
    "eq_": (mujoco.mjtObj.mjOBJ_EQUALITY, "neq"),
    "pair_": (mujoco.mjtObj.mjOBJ_PAIR, "npair"),
}
# fields that must stay >= 0 (masses, inertias, sizes, damping, friction, timestep, ...)
_NONNEGATIVE = ("body_mass", "body_inertia", "geom_size", "geom_friction", "dof_damping",
                "dof_armature", "dof_frictionloss", "jnt_stiffness", "tendon_stiffness",
                "tendon_damping", "opt.timestep", "opt.density", "opt.viscosity")


# -- distributions ------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Uniform:
    """Uniform in [low, high)."""

    low: float
    high: float

    def check(self, what: str) -> None:
        if not (np.isfinite(self.low) and np.isfinite(self.high) and self.low <= self.high):
            raise ValueError(f"{what}: Uniform expects finite low <= high, got low={self.low}, "
                             f"high={self.high}")

    def bounds(self) -> tuple[float, float]:
        return self.low, self.high

    def draw(self, d: Any, shape: tuple[int, ...], like: Any) -> Any:
        """Values of `shape` with `d` (a `simloader.draws` library: NumPy on the host, JAX in
        the jitted batch), in `like`'s dtype."""
        return d.uniform(self.low, self.high, shape, like)


@dataclasses.dataclass(frozen=True)
class LogUniform:
    """Log-uniform in [low, high): uniform in log space, for scale-like quantities."""

    low: float
    high: float

    def check(self, what: str) -> None:
        if not (np.isfinite(self.low) and np.isfinite(self.high) and 0 < self.low <= self.high):
            raise ValueError(f"{what}: LogUniform expects finite 0 < low <= high, got "
                             f"low={self.low}, high={self.high}")

    def bounds(self) -> tuple[float, float]:
        return self.low, self.high

    def draw(self, d, shape, like):
        value = d.xp.exp(d.uniform(np.log(self.low), np.log(self.high), shape, like))
        # exp may round one ulp past the bounds
        return d.clip(value, self.low, self.high)


@dataclasses.dataclass(frozen=True)
class Normal:
    """Normal(mean, std), clipped to [low, high] when given."""

    mean: float
    std: float
    low: Optional[float] = None
    high: Optional[float] = None

    def check(self, what: str) -> None:
        lo, hi = self.bounds()
        if not (np.isfinite(self.mean) and np.isfinite(self.std) and self.std >= 0 and lo <= hi):
            raise ValueError(f"{what}: Normal expects finite mean, std >= 0 and low <= high, got "
                             f"mean={self.mean}, std={self.std}, low={self.low}, high={self.high}")

    def bounds(self) -> tuple[float, float]:
        return (-np.inf if self.low is None else self.low,
                np.inf if self.high is None else self.high)

    def draw(self, d, shape, like):
        return d.clip(d.normal(shape, like) * self.std + self.mean, *self.bounds())


Distribution = Union[Uniform, LogUniform, Normal]
_OPS = ("set", "scale", "add")


@dataclasses.dataclass(frozen=True)
class Param:
    """One randomized model parameter: `field[on, index] = op(model value, draw)`.

    Attributes:
      field: an MjModel array field (`body_mass`, `geom_friction`, ...) or `opt.<name>`.
      dist: the distribution of the draw.
      op: "set" (the draw), "scale" (value * draw) or "add" (value + draw).
      on: object name(s) of the field's rows (joint names for `dof_*`); None for all rows.
      index: column(s) within each row (e.g. 0 for sliding friction); None for all.
      shared: one draw per trajectory for all the values of this parameter, instead of one each.
      name: key in `batch["params"]` (default `field[on]`).
    """

    field: str
    dist: Distribution
    op: str = "set"
    on: Names = None
    index: Any = None
    shared: bool = False
    name: Optional[str] = None

    @property
    def key(self) -> str:
        if self.name:
            return self.name
        # str() of anything else: the key also names a wrongly built Param in its error
        on = ("" if self.on is None else self.on if isinstance(self.on, str) else
              ",".join(map(str, self.on)) if isinstance(self.on, (list, tuple)) else str(self.on))
        return f"{self.field}[{on}]" if on else self.field


def set(field: str, dist: Distribution, on: Names = None, **kwargs: Any) -> Param:  # noqa: A001
    """`field = draw` for the named objects (see `Param`)."""
    return Param(field, dist, "set", on, **kwargs)


def scale(field: str, dist: Distribution, on: Names = None, **kwargs: Any) -> Param:
    """`field = model value * draw` for the named objects (see `Param`)."""
    return Param(field, dist, "scale", on, **kwargs)


def add(field: str, dist: Distribution, on: Names = None, **kwargs: Any) -> Param:
    """`field = model value + draw` for the named objects (see `Param`)."""
    return Param(field, dist, "add", on, **kwargs)


@dataclasses.dataclass(frozen=True)
class Variants:
    """Structural variants: `fn(spec, rng) -> spec` compiled into a pool of `count` models.

    Each trajectory runs on a variant drawn uniformly from the pool, and starts from that
    variant's defaults (initial state from the model or a keyframe, `mj_resetData`'s inputs);
    `batch["params"]["variant"]` holds its index. Variants must have identical sizes (same
    bodies, joints, geoms, ...); on the MJX backend they must also agree in everything MJX
    compiles in (integrator, meshes, which dofs have friction loss, ...).
    """

    fn: Callable[[mujoco.MjSpec, np.random.Generator], Optional[mujoco.MjSpec]]
    count: int = 16


# -- resolution on the host ---------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Resolved:
    """A parameter bound to a model: which flat elements of the field, and their base values."""

    param: Param
    field: str
    elements: np.ndarray  # flat indices into the field's (per-simulation) values
    base: np.ndarray  # the model's values there
    setconst: bool  # mj_setConst reads the field
    # of each value (a column of batch["params"][key]): the object it belongs to, and its
    # name (`simloader.layout.param_columns`: "pole", "floor[0]", "opt.gravity[2]")
    objects: tuple[str, ...] = ()
    columns: tuple[str, ...] = ()

    @property
    def ndraws(self) -> int:
        """Draws per trajectory, one for all values (shared), else one per value."""
        return 1 if self.param.shared else len(self.elements)

    def combine(self, base: Any, draw: Any) -> Any:
        """The values a trajectory runs with, from the model's (NumPy or JAX arrays)."""
        op = self.param.op
        return draw if op == "set" else base * draw if op == "scale" else base + draw


def _field_array(model: mujoco.MjModel, field: str) -> np.ndarray:
    if field.startswith("opt."):
        value = getattr(model.opt, field[4:], None)
        if value is not None and not callable(value):
            return np.atleast_1d(np.asarray(value, dtype=np.float64))
        names = ["opt." + n for n in dir(model.opt) if not n.startswith("_")]
    else:
        value = getattr(model, field, None)
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            return value
        names = [n for n in dir(model) if isinstance(getattr(model, n, None), np.ndarray)
                 and getattr(model, n).dtype.kind == "f"]
    raise ValueError(f"randomize: {field!r} is not a floating-point MjModel field or opt.* "
                     f"option{did_you_mean(field, names)}")


def _rows(model: mujoco.MjModel, field: str, on: Names, nrows: int) -> np.ndarray:
    if on is None:
        return np.arange(nrows)
    if field.startswith("opt."):
        raise ValueError(f"randomize: {field} has no objects; leave on=None")
    kind = next((v for k, v in _OBJECT_KINDS.items() if field.startswith(k)), None)
    if kind is None:
        raise ValueError(f"randomize: objects of {field} cannot be addressed by name; leave "
                         f"on=None and use index=")
    objtype, _ = kind
    rows = []
    for name in [on] if isinstance(on, str) else on:
        i = mujoco.mj_name2id(model, objtype, name)
        if i < 0:
            count = getattr(model, _OBJECT_KINDS["jnt_"][1] if field.startswith("dof_")
                            else kind[1])
            kind_name = objtype.name[6:].lower()
            names = [mujoco.mj_id2name(model, objtype, k) or f"{kind_name}#{k}"
                     for k in range(count)]
            hint = did_you_mean(name, names)
            plural = {"body": "bodies", "equality": "equalities"}.get(kind_name, kind_name + "s")
            raise ValueError(f"randomize: {field}: no {kind_name} named {name!r}{hint}; its "
                             f"{plural} are {names}")
        if field.startswith("dof_"):  # all dofs of the joint
            adr = int(model.jnt_dofadr[i])
            ndof = {0: 6, 1: 3}.get(int(model.jnt_type[i]), 1)
            rows.extend(range(adr, adr + ndof))
        else:
            rows.append(i)
    return np.asarray(rows)


def resolve(model: mujoco.MjModel, param: Param) -> Resolved:
    """Binds a parameter to the model, validating names, ranges and signs.

    Raises:
      TypeError, ValueError: unknown field or object (with the closest names), bad ranges,
        a draw that could make a mass, inertia, size or similar quantity negative.
    """
    if not isinstance(param, Param):
        raise TypeError(f"randomize: expected simloader.randomize parameters (scale, set, add), "
                        f"got {type(param).__name__}")
    if param.op not in _OPS:
        raise ValueError(f"randomize: op must be one of {_OPS}, got {param.op!r}")
    if not isinstance(param.dist, (Uniform, LogUniform, Normal)):
        raise TypeError(f"randomize: {param.key}: expected a Uniform, LogUniform or Normal "
                        f"distribution, got {type(param.dist).__name__}")
    param.dist.check(f"randomize: {param.key}")
    values = _field_array(model, param.field)
    table = values.reshape(values.shape[0], -1) if values.ndim else values.reshape(1, 1)
    if param.field.startswith("opt."):
        table = values.reshape(1, -1)
    rows = _rows(model, param.field, param.on, table.shape[0])
    cols = np.arange(table.shape[1]) if param.index is None else np.atleast_1d(param.index)
    if cols.size and (cols.min() < 0 or cols.max() >= table.shape[1]):
        raise ValueError(f"randomize: {param.key}: index must be in [0, {table.shape[1]}), got "
                         f"{param.index}")
    elements = (rows[:, None] * table.shape[1] + cols[None, :]).ravel()
    base = table.ravel()[elements].astype(np.float64)
    if param.field in _NONNEGATIVE:
        lo, _ = param.dist.bounds()
        smallest = {"set": np.full_like(base, lo), "scale": base * lo if lo >= 0 else -np.inf,
                    "add": base + lo}[param.op]
        if np.any(np.asarray(smallest) < 0):
            raise ValueError(f"randomize: {param.key}: the draw can make {param.field} negative "
                             f"(lowest value {np.min(smallest)}); bound the distribution: "
                             f"{_bound_hint(param, base)}")
    setconst = param.field.startswith("opt.") or param.field in mujoco.MjModel._setconst_inputs
    objects, columns = param_columns(model, param.field, rows, cols, table.shape[1])
    return Resolved(param, param.field, elements, base, setconst, objects, columns)


def _bound_hint(param: Param, base: np.ndarray) -> str:
    """How to bound `param`'s distribution so that its field stays >= 0, with an example."""
    # the lowest draw that keeps every value >= 0
    floor = -float(np.min(base)) if param.op == "add" else 0.0
    dist, name = param.dist, type(param.dist).__name__
    if isinstance(dist, Normal):
        low = max(floor, dist.mean - 3 * dist.std)
        high = dist.mean + 3 * dist.std if dist.high is None else dist.high
        how = (f"give the Normal a lower bound low= >= {floor:g} (and an upper one, high=), "
               f"to which its draws are clipped")
        bounded = f"dr.Normal({dist.mean:g}, {dist.std:g}, low={low:g}, high={high:g})"
    else:
        low = floor + 0.5 * (dist.high - floor) if dist.high > floor else floor
        how = f"give the {name} a low >= {floor:g}"
        bounded = f"dr.{name}({low:g}, {max(dist.high, low):g})"
    on = "" if param.on is None else f", on={param.on!r}"
    return f"{how}, e.g. dr.{param.op}({param.field!r}, {bounded}{on})"


class RandomizationPlan:
    """How each batch's per-trajectory model parameters are drawn (host, NumPy)."""

    def __init__(self, model: mujoco.MjModel, params: Sequence[Param]):
        self.resolved = tuple(resolve(model, p) for p in params)
        keys = [r.param.key for r in self.resolved]
        dup = sorted(builtins.set(k for k in keys if keys.count(k) > 1))
        if dup:
            raise ValueError(f"randomize: parameter names must be unique, {dup} repeat (pass "
                             f"name=...)")
        self.setconst = any(r.setconst for r in self.resolved)

    @property
    def columns(self) -> dict[str, tuple[tuple[str, ...], tuple[str, ...]]]:
        """By `batch["params"]` key, its columns as a pair (the object of each column, the
        name of each column), e.g. `(("floor",), ("floor[0]",))`."""
        return {r.param.key: (r.objects, r.columns) for r in self.resolved}

    def sample(self, seed: np.random.SeedSequence, nbatch: int) -> dict[str, np.ndarray]:
        """{key: (nbatch, nvalues)} values each trajectory runs with, one stream per param."""
        out = {}
        for r, child in zip(self.resolved, seed.spawn(len(self.resolved))):
            draw = r.param.dist.draw(draws.NumpyDraws(np.random.default_rng(child)),
                                     (nbatch, r.ndraws), np.zeros((), np.float64))
            out[r.param.key] = np.array(r.combine(r.base, np.broadcast_to(
                draw, (nbatch, len(r.elements)))))
        return out

    def sample_jax(self, key: Any, nbatch: int, dtype: Any) -> dict[str, Any]:
        """The same with `jax.random` inside a jitted function: `key` splits into one stream
        per parameter; values in `dtype` (the numbers differ from `sample`'s, the
        distributions do not)."""
        import jax
        import jax.numpy as jnp
        out, like = {}, jnp.zeros((), dtype)
        for r, k in zip(self.resolved, jax.random.split(key, len(self.resolved))):
            draw = r.param.dist.draw(draws.JaxDraws(k), (nbatch, r.ndraws), like)
            out[r.param.key] = r.combine(jnp.asarray(r.base, dtype),
                                         jnp.broadcast_to(draw, (nbatch, len(r.elements))))
        return out


def parse_randomize(model: mujoco.MjModel, randomize: Any, nbatch: int):
    """Splits the `randomize` argument into (model list, RandomizationPlan, Variants)."""
    if isinstance(randomize, (Param, Variants)):
        randomize = [randomize]
    if isinstance(randomize, (str, bytes, mujoco.MjModel)) or not isinstance(randomize, Sequence):
        raise TypeError(f"randomize: expected None, a sequence of MjModel (one per trajectory), "
                        f"simloader.randomize parameters, or Variants, got "
                        f"{type(randomize).__name__}")
    items = list(randomize)
    if items and all(isinstance(i, mujoco.MjModel) for i in items) or not items:
        return items, None, None
    variants = [i for i in items if isinstance(i, Variants)]
    params = [i for i in items if not isinstance(i, Variants)]
    if variants and params:
        raise ValueError("randomize: Variants cannot be combined with parameters; put the "
                         "parameter changes into the variant function")
    if len(variants) > 1:
        raise ValueError("randomize: give one Variants")
    if variants:
        return None, None, variants[0]
    return None, RandomizationPlan(model, params), None


def draw_variants(seed: np.random.SeedSequence, count: int, nbatch: int) -> np.ndarray:
    """Each trajectory's variant, uniform over the pool (the same on both backends)."""
    return np.random.default_rng(seed).integers(count, size=nbatch)


def compile_variants(spec: mujoco.MjSpec, variants: Variants,
                     seed: int) -> list[mujoco.MjModel]:
    """The pool of `variants.count` compiled variants (deterministic in `seed`)."""
    if isinstance(variants.count, bool) or not isinstance(variants.count, int) or \
            variants.count < 1:
        raise ValueError(f"randomize: Variants.count must be an integer >= 1, got "
                         f"{variants.count!r}")
    pool = []
    for k in range(variants.count):
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(2**31, k)))
        edited = variants.fn(spec.copy(), rng)
        try:
            pool.append((edited if edited is not None else spec).compile())
        except Exception as e:
            raise ValueError(f"randomize: variant {k} failed to compile: {e}") from e
    return pool
