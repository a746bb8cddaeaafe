"""The Warp engine's options and its checks at construction: can it run, which model arrays
differ per trajectory (model lists, variants, randomization), and MuJoCo Warp's buffer sizes.

Everything is decided on the host, in the constructing process, before any thread or worker
starts, on the models' arrays on Warp's CPU device (`model_arrays.py`): what MuJoCo Warp
supports and which of its arrays differ between the models of a pool.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, Optional

import mujoco
import numpy as np
import torch
from mujoco import rollout

from simloader import memory, observe, threads
from simloader.backends import gpu_state
from simloader.backends.warp import cameras, model_arrays, runtime
from simloader.config import SimConfig

S = mujoco.mjtState
# The mjSTATE_FULLPHYSICS components the engine simulates (time, qpos, qvel, act): the others
# must be empty (`check_simulated`, over `gpu_state.GPU_UNSIMULATED`)
# MuJoCo Warp's OverflowType bits: the solver stopping at its iteration limits (which MuJoCo C's
# does silently) is counted; every other bit means a buffer overflowed and something (contacts,
# constraint rows, collision detail) was dropped
_NEFC, _NJMAX_NNZ, _BROADPHASE, _NARROWPHASE, _CCD, _HFIELD = (1 << i for i in range(6))
SOLVER_LIMIT = (1 << 9) | (1 << 10)  # ITERATIONS, LS_ITERATIONS
# calibration of the buffers: trajectories and steps of MuJoCo C, margin over what they used
_CALIBRATION_TRAJECTORIES, _CALIBRATION_STEPS, _MARGIN = 16, 300, 2.0
# what mj_setConst derives (MuJoCo Warp's `set_const` writes these per world when they are
# per-world arrays); batched whenever a randomized field is one of its inputs
SETCONST_OUTPUTS = ("body_subtreemass", "body_invweight0", "dof_invweight0", "tendon_invweight0",
                    "tendon_length0", "actuator_acc0", "actuator_lengthrange", "geom_aabb",
                    "geom_rbound", "geom_size", "eq_data", "cam_pos0", "cam_poscom0",
                    "cam_mat0", "light_pos0", "light_poscom0", "light_dir0")


@dataclasses.dataclass(frozen=True)
class WarpOptions:
    """The Warp engine's options, resolved at construction.

    Attributes:
      naconmax, njmax: MuJoCo Warp's contact pool (whole batch) and constraint rows (per
        trajectory).
      per_world: the model arrays that differ per trajectory (`opt.` for options), sorted.
      pooled: those of `per_world` taken from each trajectory's model of a pool (a model list
        or variants) rather than written by randomization, sorted.
    """

    naconmax: int
    njmax: int
    per_world: tuple[str, ...]
    pooled: tuple[str, ...] = ()

    def simulated_by(self) -> str:
        return f"MuJoCo Warp, naconmax={self.naconmax}, njmax={self.njmax}"


def check_options(config: SimConfig, options: dict[str, Any], reason: str) -> WarpOptions:
    """Validates a Warp configuration in the constructing process.

    Args:
      config: the validated dataset configuration.
      options: keyword options of `SimDataset` beyond its own: `naconmax` and `njmax`, MuJoCo
        Warp's contact pool of the whole batch and constraint rows per trajectory (None: sized
        from the model) (JAX's options are refused by the registry: JAX does not run here).
      reason: why the Warp engine simulates (asked, or what `backend="auto"` estimated).

    Raises:
      TypeError: `naconmax` or `njmax` not None or an integer.
      ValueError: the engine cannot run here (saying what is missing), MuJoCo Warp cannot
        simulate a model, models differ in an array MuJoCo Warp shares across trajectories, a
        randomized field MuJoCo Warp cannot hold per trajectory, a record it does not keep,
        a `terminate=` rule its kernel does not evaluate.
    """
    naconmax = _positive("naconmax", options.get("naconmax"))
    njmax = _positive("njmax", options.get("njmax"))
    why = runtime.missing()
    if why:
        raise ValueError(f"backend: 'warp' cannot run here: {why}; use backend='cpu', 'mjx' "
                         f"or 'auto'")
    if config.dtype == torch.float64:
        # stacklevel: the user's line (here, the entry, binding.bind, SimDataset, the user)
        warnings.warn("dtype=torch.float64 with backend='warp': MuJoCo Warp simulates in "
                      "float32, so the tensors are float32 values up-cast to float64",
                      UserWarning, stacklevel=5)
    models = config.pool
    names = (["model"] if len(models) == 1 else
             [f"randomize[{i}]" for i in range(len(models))] if config.models is not None else
             [f"randomize: variant[{i}]" for i in range(len(models))])
    for name, model in zip(names, models):
        check_simulated(name, model)
    pooled: set[str] = set()
    randomized: set[str] = set()
    if models[0] is not config.model or len(models) > 1 or config.randomization is not None:
        # the dataset's own model alone needs no arrays here: the binding, or auto's choice,
        # asked `refuses_model` of it first, which put it (a humanoid's put is 25-50 ms of a
        # start-up)
        puts = [model_arrays.put(name, model) for name, model in zip(names, models)]
        pooled = set(_differing(puts, names))
        if config.randomization is not None:
            randomized = _randomized(config, puts[0])
    _check_records(config)
    if config.terminate is not None:
        from simloader.backends.warp import episodes
        episodes.check_rules(config.terminate)
    images = [o for o in config.observations if isinstance(o, observe.CameraImage)]
    why = cameras.refusal(images)
    if why:
        raise ValueError(f"record: backend='warp' cannot render {[o.key for o in images]}: {why}")
    # the batches in flight (prefetched, being simulated, being consumed), float32 outputs,
    # and the engine's own buffers of one batch
    device = runtime.sim_device(config.device)
    available = (torch.cuda.mem_get_info(device)[0] if device.type == "cuda"
                 else memory.host_available())
    memory.check_batch_fits(config, available, f"{device} memory", count=config.prefetch + 3,
                             itemsize=4)
    x0 = config.initial.sample(np.random.SeedSequence(config.seed), config.nbatch)
    naconmax, njmax = buffer_sizes(config.model, config.nbatch, x0, naconmax, njmax)
    return WarpOptions(naconmax, njmax, tuple(sorted(pooled | randomized)),
                       tuple(sorted(pooled - randomized)))


def _positive(name: str, value: Any) -> Optional[int]:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: expected None or a positive integer, got "
                        f"{type(value).__name__} {value!r}")
    if value < 1:
        raise ValueError(f"{name}: expected None or a positive integer, got {value}")
    return int(value)


def check_simulated(name: str, model: mujoco.MjModel) -> None:
    """Refuses a model with state the Warp engine does not simulate (`gpu_state`)."""
    unsimulated = gpu_state.unsimulated(model)
    if unsimulated:
        raise ValueError(f"{name}: the Warp engine does not simulate {unsimulated[0]}; use "
                         f"backend='cpu'")


def _differing(puts: list, names: list[str]) -> list[str]:
    """The arrays where the models of a pool differ (each must be batchable)."""
    if len(puts) == 1:
        return []
    first = {k: v.numpy() for k, v in model_arrays.arrays(puts[0]).items()}
    out = []
    for name, put in zip(names[1:], puts[1:]):
        for field, array in model_arrays.arrays(put).items():
            if field in out:
                continue
            value = array.numpy()
            if value.shape == first[field].shape and np.array_equal(value, first[field]):
                continue
            if not model_arrays.batchable(field) or value.shape[1:] != first[field].shape[1:]:
                raise ValueError(
                    f"{name}: {field} differs from {names[0]}, but with backend='warp' it cannot "
                    f"differ per trajectory (MuJoCo Warp shares it across all trajectories of "
                    f"a batch)")
            out.append(field)
    return out


def _randomized(config: SimConfig, put: Any) -> set[str]:
    """The arrays randomization writes per trajectory (and what `set_const` derives from
    them); refuses by name what MuJoCo Warp cannot hold per trajectory."""
    held = model_arrays.arrays(put)
    can = sorted(f for f in held if model_arrays.batchable(f) and held[f].dtype.__name__.startswith(
        ("float", "vec", "quat", "mat", "spatial")))
    out = set()
    for r in config.randomization.resolved:
        field = model_arrays.CONVERTED.get(r.field, (r.field,))[0]
        size = np.asarray(_mujoco_field(config.model, r.field)).size
        why = None
        if field not in held or not model_arrays.batchable(field):
            why = "MuJoCo Warp shares it across all trajectories of a batch"
        elif _per_world_size(held[field]) != size:
            why = f"MuJoCo Warp stores it in another layout ({held[field].shape})"
        if why:
            raise ValueError(f"randomize: {r.param.key}: backend='warp' cannot randomize "
                             f"{r.field} ({why}); it can randomize {', '.join(can)} "
                             f"(backend='cpu' any floating-point field)")
        out.add(field)
    if config.randomization.setconst:
        out |= {f for f in SETCONST_OUTPUTS if f in held and model_arrays.batchable(f)}
    return out


def _mujoco_field(model: mujoco.MjModel, field: str) -> Any:
    return getattr(model.opt, field[4:]) if field.startswith("opt.") else getattr(model, field)


def _per_world_size(array: Any) -> int:
    """Scalars one world holds in a (1, ...) model array (vector dtypes unrolled)."""
    return int(np.prod(array.shape[1:])) * int(np.prod(getattr(array.dtype, "_shape_", ())))


def _check_records(config: SimConfig) -> None:
    """Every recorded field must be one MuJoCo Warp's Data holds under MuJoCo's name."""
    import mujoco_warp as mjw
    held = {f.name for f in dataclasses.fields(mjw.Data)}
    for o in config.observations:
        if isinstance(o, observe.CameraImage):
            continue
        missing = sorted(set(o.fields()) - held)
        if missing:
            raise ValueError(f"record: {o.key!r}: MuJoCo Warp has no field {missing[0]} "
                             f"(backend='warp'); use backend='mjx' or backend='cpu'")


def buffer_sizes(model: mujoco.MjModel, nbatch: int, x0: np.ndarray,
                 naconmax: Optional[int], njmax: Optional[int]) -> tuple[int, int]:
    """(naconmax, njmax) for `nbatch` trajectories: the user's values, else measured.

    Measured: MuJoCo C runs `_CALIBRATION_TRAJECTORIES` trajectories (from initial states `x0`,
    (n, nstate)) under uniform random controls for `_CALIBRATION_STEPS` steps; each buffer gets
    twice the most a trajectory used, and at least MuJoCo Warp's own per-world guess.
    """
    # private: MuJoCo Warp's own per-world guesses of the buffer sizes (what `make_data`
    # takes without sizes), kept as the floor of ours; not exported
    from mujoco_warp._src import io as warp_io
    if naconmax is not None and njmax is not None:
        return naconmax, njmax
    ncon, nefc = _calibrate(model, x0)
    per_world_contacts = max(warp_io._default_nconmax(model), int(np.ceil(_MARGIN * ncon)))
    rows = max(warp_io._default_njmax(model), int(np.ceil(_MARGIN * nefc)))
    return (naconmax if naconmax is not None else nbatch * per_world_contacts,
            njmax if njmax is not None else rows)


def _calibrate(model: mujoco.MjModel, x0: np.ndarray) -> tuple[int, int]:
    """The most contacts and constraint rows one trajectory of MuJoCo C used.

    One `mujoco.rollout` call (all in C, on threads: a Python loop of `mj_step` on threads was
    about 0.1 s of a warm first batch on a 16-core GPU host, its threads taking turns at the
    GIL every step), read back from MuJoCo's own high-water marks: `maxuse_con` and
    `maxuse_efc` of each thread's MjData, the most any of its steps used (the same sizes the
    loop measured after every step, on 17 robot models). The controls are drawn from one
    generator in trajectory order, as before: the sizes are those the suite measured on an
    H200 (njmax 64 for the humanoid; draws of another order gave 70, and a run of the cameras
    workload then the randomized one hit an illegal memory access there)."""
    low, high = np.where(model.actuator_ctrllimited[:, None].astype(bool), model.actuator_ctrlrange,
                         [-1.0, 1.0]).T
    n = min(_CALIBRATION_TRAJECTORIES, len(x0))
    controls = np.random.default_rng(0).uniform(low, high, (n, _CALIBRATION_STEPS, model.nu))
    datas = [mujoco.MjData(model) for _ in range(min(n, threads.available_cpus()))]
    rollout.rollout(model, datas, np.asarray(x0[:n], dtype=np.float64), controls,
                    nstep=_CALIBRATION_STEPS)
    return max(d.maxuse_con for d in datas), max(d.maxuse_efc for d in datas)


def overflow_message(bits: int, naconmax: int, njmax: int) -> str:
    """What overflowed, and what to raise."""
    advice = []
    if bits & (_BROADPHASE | _NARROWPHASE | _CCD | _HFIELD):
        advice.append(f"contacts exceeded naconmax={naconmax} (the pool of the whole batch): "
                      f"pass a larger naconmax=")
    if bits & (_NEFC | _NJMAX_NNZ):
        advice.append(f"constraint rows exceeded njmax={njmax} per trajectory: pass a larger "
                      f"njmax=")
    return "; ".join(advice)
