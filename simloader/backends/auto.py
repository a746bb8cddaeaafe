"""`backend="auto"`: which engine runs fastest for this model, these sizes and this machine.

The choice is an estimate of each candidate's steps per second, from a rule measured on the
machines in `benchmarks/results/auto_choice-*.md` (`benchmarks/experiments/auto_choice.py` prints the rule's
estimate next to every engine's measured throughput and says whether `auto` chose the fastest):

- the CPU engine runs `min(nbatch, cores)` trajectories at once, each at this model's own
  single-thread `mj_step` rate, timed here in a few milliseconds (`cpu_step_seconds`), times
  an efficiency (threads share caches and memory bandwidth: `cpu/entry.py`);
- a GPU engine takes `floor + nbatch * cost` seconds per step of the batch: `floor` the fixed
  latency of launching one step (kernels, a CUDA graph's replay, XLA's loop), `cost` what one
  more trajectory adds once the GPU is busy; both scale with the model's own step time on one
  CPU core (`gpu_rule.py`; each engine's constants in its `entry.py`, fitted for models with
  and without contacts);
- a policy in the loop and cameras scale each engine's rate by its own measured factor;
- start-up (MJX's compilation, MuJoCo Warp's kernels) counts against the steps of a stream
  of known length, and against an endless stream's first minute (`FIRST_MINUTE_S`): a
  faster steady state is worth a compilation only if it wins within a minute; engines
  within 10% of each other (`NEAR_TIE`) are a tie, which the one that starts first wins.

Each registered engine answers for itself (`Engine.estimate` in `contract.py`), so an engine
from outside simloader competes on the same terms.

So a small batch belongs on the CPU (the GPU's fixed latency dominates), a large one on a GPU
engine, and the crossing moves with the model: MJX-JAX wins contact-free models (XLA fuses
the whole step), MuJoCo Warp contact-rich ones. Cameras render only on the CPU engine and on
MuJoCo Warp. Without a GPU, MJX on JAX's CPU competes too: it beat MuJoCo's own threads on
the tiny contact-free cart-pole from about 50 trajectories on (2-core machine), and lost 7x
on the humanoid. Nothing here starts JAX unless MJX is the estimate's choice.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import mujoco
import numpy as np

from simloader import backends, identity, observe, threads
from simloader.backends.contract import Job


# The wall time an endless stream is judged over: a user's first minute (a first batch,
# a first look at the loss), start-up included
FIRST_MINUTE_S = 60.0
# engines estimated within this fraction of the fastest are a tie, which the one that starts
# first wins: the estimates' error on the 2-core machine (64 cart-poles: the CPU engine and
# MJX on JAX's CPU measured 0.37-0.51M and 0.50-0.67M steps/s in three runs)
NEAR_TIE = 0.9


def first_minute_steps(rate: float, startup_s: float) -> float:
    """The steps an engine of steady `rate` steps/s delivers in an endless stream's first
    minute (`FIRST_MINUTE_S`) when it takes `startup_s` seconds to start."""
    return rate * max(0.0, FIRST_MINUTE_S - startup_s)


@dataclasses.dataclass(frozen=True)
class Choice:
    """The engine a dataset runs, and why (`describe()` says it)."""

    backend: str
    reason: str


def has_contacts(model: mujoco.MjModel) -> bool:
    """Whether any two geoms may collide (explicit pairs, or contype/conaffinity filtering of
    geoms on different bodies), unless contacts are disabled."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    if model.npair:
        return True
    body = model.geom_bodyid
    contype, conaffinity = model.geom_contype, model.geom_conaffinity
    mask = ((contype[:, None] & conaffinity[None, :]) | (conaffinity[:, None] & contype[None, :]))
    mask = (mask != 0) & (body[:, None] != body[None, :])
    return bool(np.triu(mask, 1).any())


def cpu_step_seconds(model: mujoco.MjModel, budget_s: float = 0.02) -> float:
    """This model's `mj_step` time on one core: the best of a few timed runs from its
    default state with zero controls, within about `budget_s` seconds."""
    # by the model's digest (its saved bytes): a cache by object id would outlive the model
    key = identity.model_digest(model)
    if key not in _STEP_SECONDS:
        _STEP_SECONDS[key] = _time_steps(model, budget_s)
    return _STEP_SECONDS[key]


_STEP_SECONDS: dict[str, float] = {}


def _time_steps(model: mujoco.MjModel, budget_s: float) -> float:
    # in C (mujoco.rollout, one thread), as the CPU engine steps: a Python loop of mj_step
    # calls would add a microsecond of call overhead, more than a small model's whole step
    from mujoco import rollout
    data = mujoco.MjData(model)
    spec = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
    x0 = np.empty((1, mujoco.mj_stateSize(model, spec)))
    mujoco.mj_getState(model, data, x0[0], spec)
    best, spent, nstep = float("inf"), 0.0, 50
    while spent < budget_s:
        start = time.perf_counter()
        rollout.rollout(model, data, x0, nstep=nstep)
        took = time.perf_counter() - start
        spent += took
        best = min(best, took / nstep)
        nstep = min(nstep * 2, 1000)
    return best


def candidates() -> dict[str, str]:
    """{engine: why it cannot run here, or ""} for every registered engine."""
    return {name: backends.engine(name).missing() or "" for name in backends.ENGINES}


def choose(asked: str, gpu_only: bool, probe: Any) -> Choice:
    """The engine for `asked` (a name, or "auto"), and why.

    Args:
      asked: a registered engine's name, or "auto".
      gpu_only: the older `impl="auto"`: the CPU engine may not be chosen.
      probe: what the rule looks at: `model` (the base MjModel), `nbatch`, `nstep`,
        `num_batches` (None: endless), `observations`, `policy`, `deterministic` (only the
        engines that promise bit-identical batches for the model).

    Raises:
      ValueError: no engine can run here (with `gpu_only`: no GPU engine; with
        `deterministic`: none that promises it), each one's reason said.
    """
    if asked != "auto":
        return Choice(asked, "asked")
    engines = {name: backends.engine(name) for name in backends.ENGINES}
    why = candidates()
    if gpu_only:
        why["cpu"] = "the GPU engines only (impl='auto')"
    if getattr(probe, "deterministic", False):  # only engines that promise it for the model
        for name in engines:
            if not why[name]:
                refusal = engines[name].refuses_determinism(probe.model)
                if refusal is not None:
                    why[name] = f"deterministic=True: {refusal}"
    cameras = any(isinstance(o, observe.CameraImage) for o in probe.observations)
    running = [name for name in engines if not why[name]]
    if not running:
        said = "; ".join(f"{n}: {w}" for n, w in why.items() if n != "cpu" or not gpu_only)
        raise ValueError(f"backend: no engine can run this dataset here ({said})"
                         + ("; use backend='cpu'" if gpu_only else ""))
    if len(running) == 1:
        said = "; ".join(f"{n}: {w}" for n, w in why.items() if w)
        # asked as a chosen engine is, so that the model is refused at construction (and
        # an engine's checks may rely on it having been asked)
        refusal = engines[running[0]].refuses_model(probe.model)
        if refusal is not None:
            raise ValueError(f"backend: no engine can run this dataset here ({said}; "
                             f"{running[0]}: {refusal})")
        return Choice(running[0], f"auto: the only engine that runs here ({said})")
    cores = threads.available_cpus()
    steps = (None if probe.num_batches is None else
             probe.nbatch * probe.nstep * probe.num_batches)
    job = Job(step_s=cpu_step_seconds(probe.model), nbatch=probe.nbatch,
              contacts=has_contacts(probe.model), cores=cores,
              policy=probe.policy is not None, cameras=cameras, steps=steps,
              episodes=getattr(probe, "terminate", None) is not None,
              episode_callable=getattr(getattr(probe, "terminate", None), "check", None)
              is not None)
    rates = {name: rate for name in running
             if (rate := engines[name].estimate(job)) is not None}
    startup = {name: engines[name].startup_s(job) for name in rates}
    if steps is not None:
        # a stream of known length: the steps over start-up plus simulation
        rates = {name: steps / (startup[name] + steps / rate) for name, rate in rates.items()}
    else:
        # an endless stream: the steps of its first minute, start-up included. Counting
        # start-up against forever sent 64 x 100 cart-poles to a 9 s MJX compilation on a
        # 2-core machine for a 2% faster steady state (benchmarks/results/auto_choice-*)
        rates = {name: first_minute_steps(rate, startup[name]) / FIRST_MINUTE_S
                 for name, rate in rates.items()}
    if not rates:
        raise ValueError(f"backend: no engine that runs here can simulate this dataset "
                         f"({', '.join(running)}; cameras: {cameras})")
    # a near tie (within NEAR_TIE, less than the rule's error) goes to the engine that starts
    # first: its first batch comes at once, and the estimate cannot tell the two apart
    top = max(rates.values())
    near = {name for name, rate in rates.items() if rate >= NEAR_TIE * top}
    order = sorted(rates, key=lambda n: (n not in near, startup[n] if n in near else 0.0,
                                         -rates[n]))
    passed: dict[str, str] = {}
    for best in order:
        # an engine that cannot simulate the model is passed over: asked only of the engine
        # about to be chosen (MJX's answer imports JAX, which a CPU choice never needs)
        refusal = engines[best].refuses_model(probe.model)
        if refusal is not None:
            passed[best] = f"refuses this model: {refusal}"
            continue
        if not engines[best].confirm():  # may start the runtime (JAX asked for its GPUs)
            break
    if best in passed:  # the last one refused too: the best of those that did not
        left = [name for name in order if name not in passed]
        if not left:
            raise ValueError("backend: every engine that runs here refuses this model ("
                             + "; ".join(f"{n}: {w}" for n, w in passed.items()) + ")")
        best = left[0]
    said = ", ".join(f"{name} ~{rates[name] / 1e6:.2g}M" for name in order)
    gpu = " and this GPU" if backends.gpu_visible() else ""
    length = (f", over an endless stream's first {FIRST_MINUTE_S:.0f} s with a first run's "
              f"start-up" if steps is None else
              f", over this stream's {steps / 1e6:.3g}M steps with a first run's start-up")
    over = "; ".join(f"{n}: {w}" for n, w in passed.items())
    return Choice(best, f"auto: estimated steps/s for nbatch={probe.nbatch} on {cores} "
                        f"cores{gpu}{length}: {said} (rule in simloader/backends/auto.py)"
                        + (f"; passed over: {over}" if over else ""))
