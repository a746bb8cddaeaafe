"""Validating `SimDataset`'s arguments, once, on the host, into one frozen configuration.

Checks run in a fixed order (types, sizes, models, control, initial state) and raise
`TypeError`/`ValueError` naming the argument, the expectation and what was given, before any
thread, worker or compilation starts.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, Optional

import mujoco
import numpy as np
import torch

from simloader import controls, initial, layout, models, observe, threads
from simloader import policy as simloader_policy
from simloader import randomize as dr
from simloader import terminate as terminate_rules

@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings:
    """`SimDataset`'s arguments, validated without any engine (`validate`): everything an
    engine is chosen for and checks, and then simulates from.

    Attributes:
      model: the model (the first of `models` when a list was given).
      models: one MjModel per trajectory (`randomize` as a list), or None.
      randomization: per-trajectory model parameters drawn every batch, or None.
      variants: the pool of compiled structural variants sampled per trajectory, or None.
      nbatch, nstep, nstate, ncontrol, nsensordata: sizes, MuJoCo's words.
      control_spec: the mjtState bits of the control vector.
      control: how each batch's controls are made.
      initial: how each batch's initial states are made.
      observations: what each batch records (`record=`), in the order given.
      record_every: frames are recorded after every `record_every`-th step.
      record_kinematics: "before_step" (the derived fields as `mj_step` leaves them) or
        "frame" (as `mj_forward` computes them at the frame's own state).
      frame_stage: with "frame", the forward stage (`mjtStage`) an engine computes at every
        recorded frame so that its records describe the frame (`records.frame_stage`); None:
        none (the default, or records that derive nothing).
      continue_episodes: batches continue the previous batch's trajectories.
      num_batches: batches per rank in total, or None for endless.
      seed: root of all randomness.
      device, dtype: where and in what the tensors are delivered (None: backend native).
      nthread: CPU threads of the CPU engine (None: the cores split among workers).
      prefetch: batches simulated ahead of the consumer.
      torch_threads: torch's intra-op threads in the constructing process (the consumer's).
      policy: closed loop: the callable that picks every step's controls, or None.
      policy_noise: closed loop: exploration noise added to the policy's controls, drawn as
        `control` generators draw (a plan whose undriven columns are 0), or None.
      deterministic: the same seed must give bit-identical batches (the engine bound to it
        promised it for this model, `Engine.refuses_determinism`).
      terminate: the rules that end an episode (`simloader.terminate.Episodes`, autoreset on
        the next frame), or None: every trajectory runs its `nstep` steps.
    """

    model: mujoco.MjModel
    models: Optional[tuple[mujoco.MjModel, ...]]
    nbatch: int
    nstep: int
    nstate: int
    ncontrol: int
    nsensordata: int
    control_spec: int
    randomization: Optional[dr.RandomizationPlan]
    variants: Optional[tuple[mujoco.MjModel, ...]]
    control: controls.ControlPlan
    initial: initial.InitialPlan
    observations: tuple[observe.Observation, ...]
    record_every: int
    continue_episodes: bool
    num_batches: Optional[int]
    seed: int
    device: Optional[torch.device]
    dtype: Optional[torch.dtype]
    nthread: Optional[int]
    prefetch: int
    torch_threads: int = 1  # torch's intra-op threads where the dataset was made (the trainer)
    policy: Any = None
    policy_noise: Optional[controls.ControlPlan] = None
    deterministic: bool = False
    terminate: Optional[terminate_rules.Episodes] = None
    record_kinematics: str = "before_step"
    frame_stage: Optional[int] = None

    @property
    def pool(self) -> tuple[mujoco.MjModel, ...]:
        """The models trajectories pick from: the model list, the variant pool, or the
        model (every engine's per-model tables are built over it)."""
        return tuple(self.models or self.variants or (self.model,))

    @property
    def nframes(self) -> int:
        """Recorded frames per trajectory per batch: `nstep // record_every`."""
        return self.nstep // self.record_every

    def model_tables(self, spec: int) -> "ModelTables":
        """What every engine starts a trajectory from, per model of `pool` (NumPy, float64;
        each engine puts them where it simulates). `spec`: the mjtState bits of the reset
        rows (the engine's state row)."""
        variants = self.variants is not None
        variant_states = (initial.default_states(self.variants, self.initial.keyframe)
                          if variants and self.initial.from_model else None)
        low, high = controls.applied_bounds(self.pool, self.control_spec)
        # with variants, each one's undriven control columns as mj_resetData leaves them
        control_defaults = (layout.reset_rows(self.variants, self.control_spec) if variants
                            else self.control.default_rows)
        return ModelTables(layout.reset_rows(self.pool, spec), control_defaults,
                           variant_states, low, high)


@dataclasses.dataclass(frozen=True, kw_only=True)
class SimConfig(Settings):
    """Everything a backend needs to simulate one batch: the `Settings` and the engine bound
    to them (`simloader.backends.binding.bind`), complete when it is built.

    Attributes:
      backend: the engine that simulates (a registered engine's name; "auto" resolved);
        `backend_reason`: why ("asked", or what "auto" estimated).
      options: the engine's own options as it resolved them (buffer sizes, caches, and
        `simulated_by()`).
      parts: when the batch is simulated on other devices than `device` (`sim_device=`): one
        configuration per simulation device, each with its share of the trajectories in
        order (`nbatch`) and that device as its `device`; None: simulated where delivered.
    """

    backend: str
    backend_reason: str
    options: Any
    parts: Optional[tuple["SimConfig", ...]] = None

    @classmethod
    def bound(cls, settings: Settings, **engine: Any) -> "SimConfig":
        """`settings` with the engine's fields (`backend`, `backend_reason`, `options`,
        `parts`)."""
        return cls(**{f.name: getattr(settings, f.name)
                      for f in dataclasses.fields(Settings)}, **engine)


@dataclasses.dataclass(frozen=True)
class ModelTables:
    """Per model of `SimConfig.pool` (the model list, the variants, or the one model).

    Attributes:
      reset_rows: (npool, nspec): each model's state rows as mj_resetData leaves them.
      control_defaults: ([npool or 1], ncontrol): the control columns no generator drives.
      variant_states: with variants and initial states from the model, (nvariant, nstate)
        each variant's; else None.
      low, high: (npool, ncontrol): the range MuJoCo clamps each control column to.
    """

    reset_rows: np.ndarray
    control_defaults: np.ndarray
    variant_states: Optional[np.ndarray]
    low: np.ndarray
    high: np.ndarray


def _int(name: str, value: Any, low: int, allow_none: bool = False) -> Optional[int]:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        kind = "an integer or None" if allow_none else "an integer"
        raise TypeError(f"{name}: expected {kind}, got {type(value).__name__} {value!r}")
    if value < low:
        kind = "None or an integer" if allow_none else "an integer"
        raise ValueError(f"{name}: expected {kind} >= {low}, got {value}")
    return int(value)


def _check_same_sizes(model: mujoco.MjModel, models: Sequence[mujoco.MjModel], what: str,
                      control_spec: int) -> None:
    sizes = ("nq", "nv", "nu", "na", "nbody", "njnt", "ngeom", "nsensordata", "nmocap", "neq",
             "nuserdata", "nhistory", "nplugin")
    for i, m in enumerate(models):
        if not isinstance(m, mujoco.MjModel):
            raise TypeError(f"{what}[{i}]: expected an MjModel, got {type(m).__name__}")
        for s in sizes:
            if getattr(m, s, None) != getattr(model, s, None):
                raise ValueError(f"{what}[{i}]: models must have identical sizes; {s} is "
                                 f"{getattr(m, s)}, expected {getattr(model, s)} (as the base "
                                 f"model)")
        for spec in (layout.FULLPHYSICS, layout.INTEGRATION, control_spec):
            if mujoco.mj_stateSize(m, spec) != mujoco.mj_stateSize(model, spec):
                raise ValueError(f"{what}[{i}]: state size for spec {spec} differs from the "
                                 f"base model")


def _randomization(model_arg: Any, model: mujoco.MjModel, randomize: Any, nbatch: int,
                   control_spec: int, seed: int):
    """(model list, RandomizationPlan, variant pool) from the `randomize` argument."""
    if randomize is None:
        return None, None, None
    models_, plan, variants = dr.parse_randomize(model, randomize, nbatch)
    if models_ is not None:
        if len(models_) != nbatch:
            raise ValueError(f"randomize: expected nbatch={nbatch} models (one per trajectory), "
                             f"got {len(models_)}")
        _check_same_sizes(model, models_, "randomize", control_spec)
        return tuple(models_), None, None
    if variants is not None:
        spec = models.load_spec(model_arg)
        pool = dr.compile_variants(spec, variants, seed)
        _check_same_sizes(pool[0], pool, "randomize: variant", control_spec)
        return None, None, tuple(pool)
    return None, plan, None


def _torch_device(device: Any, name: str = "device",
                  none: bool = True) -> Optional[torch.device]:
    """`device` as a torch device torch can use here, named `name` in errors: a cpu device, or
    a cuda device of a GPU torch sees (None stays None where `none`)."""
    if device is None and none:
        return None
    allowed = "None, 'cpu', 'cuda' or 'cuda:N'" if none else "'cpu', 'cuda' or 'cuda:N'"
    if isinstance(device, (bytes, bytearray)):
        # torch.device would take b"cpu" as is; a device is named by a str
        raise ValueError(f"{name}: expected {allowed} (a str or a torch.device), got bytes "
                         f"{device!r}; decode it first")
    try:
        dev = torch.device(device)
    except (TypeError, RuntimeError) as e:
        raise ValueError(f"{name}: expected {allowed}, got {device!r}") from e
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{name}: expected a cpu or cuda device, got {device!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{name}: {device!r} requested but torch sees no CUDA device")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{name}: {device!r} requested but torch sees "
                             f"{torch.cuda.device_count()} GPU(s)")
    return dev


def _torch_dtype(dtype: Any) -> Optional[torch.dtype]:
    if dtype is None:
        return None
    half = (torch.float16, torch.bfloat16, np.float16, "float16", "bfloat16", "half")
    if any(dtype is h or (isinstance(dtype, str) and dtype == h) for h in half):
        raise ValueError(f"dtype: {dtype} (half precision) cannot hold simulation states: 3 "
                         f"significant digits, and float16 overflows above 65504 and rounds "
                         f"time steps away; use torch.float32 or torch.float64 and convert "
                         f"in your model")
    allowed = {torch.float64: torch.float64, torch.float32: torch.float32,
               np.float64: torch.float64, np.float32: torch.float32,
               "float64": torch.float64, "float32": torch.float32}
    try:
        out = allowed[dtype]
    except (KeyError, TypeError):
        raise ValueError(f"dtype: expected None, torch.float32 or torch.float64, got "
                         f"{dtype!r}") from None
    return out  # the GPU engines say what float64 means for them (their check_options)


def _record(model: mujoco.MjModel, record: Any, record_every: Any, nstep: int,
            kinematics: Any) -> tuple[tuple[observe.Observation, ...], int, Optional[int]]:
    """The observations `record` names, the validated `record_every`, and the forward stage
    `record_kinematics` asks at every frame (None: none)."""
    observations = observe.parse(model, record)
    record_every = _int("record_every", record_every, 1)
    if nstep % record_every:
        raise ValueError(f"record_every: nstep={nstep} must be a multiple of record_every, got "
                         f"record_every={record_every} (frame j holds the values after step "
                         f"(j + 1) * record_every)")
    if not isinstance(kinematics, str) or kinematics not in observe.KINEMATICS:
        raise ValueError(f"record_kinematics: expected one of {observe.KINEMATICS} (the "
                         f"derived fields of the state before the step, as mj_step leaves "
                         f"them, or those of the frame itself, as mj_forward computes them), "
                         f"got {kinematics!r}")
    stage = observe.frame_stage(model, observations) if kinematics == "frame" else None
    return observations, record_every, stage


def _policy(policy: Any, noise: Any, control: Any, model: mujoco.MjModel, control_spec: int,
            nbatch: int, nstep: int) -> Optional[controls.ControlPlan]:
    """Validates the closed loop's arguments; returns the noise plan (None without noise)."""
    if policy is None:
        if noise is not None:
            raise ValueError("policy_noise: is exploration noise around a policy's controls and "
                             "needs policy=; for open-loop noise pass it as control=")
        return None
    simloader_policy.check(policy)
    if control is not None:
        raise ValueError(f"control, policy: the policy picks every step's controls, so control "
                         f"must be None, got {type(control).__name__}; for exploration noise "
                         f"around the policy pass a generator as policy_noise=")
    if noise is None:
        return None
    plan = controls.ControlPlan(model, control_spec, noise, nbatch, nstep)
    if plan.fixed is not None:
        raise TypeError(f"policy_noise: expected a simloader.controls generator or a dict "
                        f"{{component: generator}}, got {type(noise).__name__}")
    # noise is added: the columns no generator drives get none
    plan.default_rows = np.zeros_like(plan.default_rows)
    return plan


def _deterministic(deterministic: Any) -> bool:
    if deterministic is None:  # as the training's own torch code is asked to be
        return torch.are_deterministic_algorithms_enabled()
    if not isinstance(deterministic, bool):
        raise TypeError(f"deterministic: expected None (follow torch."
                        f"are_deterministic_algorithms_enabled()), True or False, got "
                        f"{type(deterministic).__name__} {deterministic!r}")
    return deterministic


def sim_devices(sim_device: Any, device: Optional[torch.device]
                ) -> tuple[Optional[torch.device], Optional[tuple[torch.device, ...]]]:
    """(where batches are delivered, where they are simulated) from `device` (validated) and
    `sim_device`: None when simulated where delivered. A device named twice simulates two
    parts of the batch there. With `sim_device` and no `device`, batches are delivered to
    torch's current CUDA device (where a training loop runs by default)."""
    if sim_device is None:
        return device, None
    listed = (list(sim_device) if isinstance(sim_device, (list, tuple)) else [sim_device])
    if not listed:
        raise ValueError("sim_device: expected a device or a non-empty sequence of devices, "
                         "got an empty sequence")
    parsed = []
    for i, d in enumerate(listed):
        name = f"sim_device[{i}]" if isinstance(sim_device, (list, tuple)) else "sim_device"
        dev = _torch_device(d, name, none=False)
        if dev.type == "cuda" and dev.index is None:  # parts on one device compare equal
            dev = torch.device("cuda", torch.cuda.current_device())
        parsed.append(dev)
    if device is None:
        device = (torch.device("cuda", torch.cuda.current_device())
                  if torch.cuda.is_available() else torch.device("cpu"))
    if parsed == [device]:
        return device, None  # simulated where delivered
    return device, tuple(parsed)


def split_sizes(nbatch: int, parts: int) -> list[int]:
    """Trajectories of each part of a batch split `parts` ways: as even as can be, the
    first ones one larger."""
    return [nbatch // parts + (i < nbatch % parts) for i in range(parts)]


def _part_of(value: Any, nbatch: int, start: int, stop: int, ndim: int) -> Any:
    """An argument's rows `start:stop` where it has one per trajectory (an array of `ndim`
    dimensions with nbatch rows, or a list of nbatch models); else the argument itself."""
    if isinstance(value, (list, tuple)) and len(value) == nbatch and value and all(
            isinstance(m, mujoco.MjModel) for m in value):
        return list(value[start:stop])
    shape = getattr(value, "shape", None)
    if shape is not None and len(shape) == ndim and shape[0] == nbatch and nbatch > 1:
        return value[start:stop]
    return value


def validate(model: Any, *, nbatch: Any, nstep: Any, control: Any, control_spec: Any,
             initial_state: Any, randomize: Any, continue_episodes: Any, num_batches: Any,
             seed: Any, device: Any, dtype: Any, nthread: Any, prefetch: Any, record: Any,
             record_every: Any, policy: Any = None, policy_noise: Any = None,
             deterministic: Any = False, sim_device: Any = None, terminate: Any = None,
             record_kinematics: Any = "before_step"
             ) -> tuple[Settings, Optional[tuple[Settings, ...]]]:
    """Validates `SimDataset`'s arguments (see its docstring), engine-free and in one pass,
    into `Settings`; with `sim_device`, also one `Settings` per simulation device (each its
    share of the trajectories, in order, the same arguments over its rows of the
    per-trajectory ones, that device as its `device`); None otherwise. The engine is bound to
    them afterwards (`simloader.backends.binding.bind`)."""
    arguments = dict(nstep=nstep, control_spec=control_spec, continue_episodes=continue_episodes,
                     num_batches=num_batches, seed=seed, dtype=dtype, nthread=nthread,
                     prefetch=prefetch, record=record, record_every=record_every,
                     policy=policy, policy_noise=policy_noise, deterministic=deterministic,
                     terminate=terminate, record_kinematics=record_kinematics)
    whole = _settings(model, nbatch=nbatch, control=control, initial_state=initial_state,
                      randomize=randomize, device=_torch_device(device), **arguments)
    target, simulated_on = sim_devices(sim_device, whole.device)
    if simulated_on is None:
        return whole, None
    if len(simulated_on) > whole.nbatch:
        raise ValueError(f"sim_device: {len(simulated_on)} simulation devices for nbatch="
                         f"{whole.nbatch} trajectories; each device needs at least one")
    whole = dataclasses.replace(whole, device=target)
    parts, start = [], 0
    for dev, n in zip(simulated_on, split_sizes(whole.nbatch, len(simulated_on))):
        stop = start + n
        parts.append(_settings(
            model, nbatch=n, control=_part_of(control, whole.nbatch, start, stop, 3),
            initial_state=_part_of(initial_state, whole.nbatch, start, stop, 2),
            randomize=_part_of(randomize, whole.nbatch, start, stop, 1), device=dev,
            **arguments))
        start = stop
    return whole, tuple(parts)


def _settings(model: Any, *, nbatch: Any, nstep: Any, control: Any, control_spec: Any,
              initial_state: Any, randomize: Any, continue_episodes: Any, num_batches: Any,
              seed: Any, device: Optional[torch.device], dtype: Any, nthread: Any,
              prefetch: Any, record: Any, record_every: Any, policy: Any, policy_noise: Any,
              deterministic: Any, terminate: Any, record_kinematics: Any) -> Settings:
    """The arguments of one batch (or one simulation device's part of it), validated."""
    nbatch = _int("nbatch", nbatch, 1)
    nstep = _int("nstep", nstep, 1)
    # 0 batches would be a dataset that silently yields nothing
    num_batches = _int("num_batches", num_batches, 1, allow_none=True)
    seed = _int("seed", seed, 0)
    nthread = _int("nthread", nthread, 1, allow_none=True)
    threads.check_nthread(nthread)
    prefetch = _int("prefetch", prefetch, 1)
    if not isinstance(continue_episodes, bool):
        raise TypeError(f"continue_episodes: expected a bool, got "
                        f"{type(continue_episodes).__name__}")
    if isinstance(control_spec, str):
        control_spec = layout.parse_control_spec(control_spec)
    if isinstance(control_spec, bool) or not isinstance(control_spec, (int, np.integer,
                                                                        mujoco.mjtState)):
        raise TypeError(f"control_spec: expected an mjtState bitmask (int) or component names "
                        f"('ctrl|xfrc_applied'), got {type(control_spec).__name__}")
    control_spec = int(control_spec)
    if control_spec & ~layout.USER or control_spec < 0:
        raise ValueError(f"control_spec: expected bits within mjSTATE_USER ({layout.USER}), got "
                         f"{control_spec} (bits {control_spec & ~layout.USER} are outside)")
    base = models.load_model(model)
    models_, randomization, variants = _randomization(model, base, randomize, nbatch,
                                                      control_spec, seed)
    if models_ is not None:
        base = models_[0]
    elif variants is not None:
        base = variants[0]
    observations, record_every, stage = _record(base, record, record_every, nstep,
                                                record_kinematics)
    deterministic = _deterministic(deterministic)
    plan = controls.ControlPlan(base, control_spec, control, nbatch, nstep, models_)
    init = initial.InitialPlan(base, initial_state, nbatch, models_)
    noise = _policy(policy, policy_noise, control, base, control_spec, nbatch, nstep)
    return Settings(
        model=base, models=models_, nbatch=nbatch, nstep=nstep,
        nstate=mujoco.mj_stateSize(base, layout.FULLPHYSICS), ncontrol=plan.ncontrol,
        nsensordata=base.nsensordata, control_spec=control_spec, randomization=randomization,
        variants=variants, control=plan, initial=init, observations=observations,
        record_every=record_every, continue_episodes=continue_episodes,
        num_batches=num_batches, seed=seed, device=device,
        dtype=_torch_dtype(dtype), nthread=nthread, prefetch=prefetch,
        torch_threads=torch.get_num_threads(), policy=policy, policy_noise=noise,
        deterministic=deterministic, terminate=terminate_rules.parse(base, terminate),
        record_kinematics=record_kinematics, frame_stage=stage)
