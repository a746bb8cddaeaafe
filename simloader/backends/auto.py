"""`backend="auto"`: which engine runs fastest for this model, these sizes and this machine.

The choice is an estimate of each candidate's steps per second, from a rule measured on the
machines in `benchmarks/results/auto_choice-*.md` (`benchmarks/auto_choice.py` prints the rule's
estimate next to every engine's measured throughput and says whether `auto` chose the fastest):

- the CPU engine runs `min(nbatch, cores)` trajectories at once, each at this model's own
  single-thread `mj_step` rate, timed here in a few milliseconds (`cpu_step_seconds`), times
  `CPU_EFFICIENCY` (threads share caches and memory bandwidth);
- a GPU engine takes `floor + nbatch * cost` seconds per step of the batch: `floor` the fixed
  latency of launching one step (kernels, a CUDA graph's replay, XLA's loop), `cost` what one
  more trajectory adds once the GPU is busy; both scale with the model's own step time on one
  CPU core (`GPU_RULE`, fitted per engine and for models with and without contacts).

So a small batch belongs on the CPU (the GPU's fixed latency dominates), a large one on a GPU
engine, and the crossing moves with the model: MJX-JAX wins contact-free models (XLA fuses
the whole step), MuJoCo Warp contact-rich ones. Cameras render only on the CPU engine and on
MuJoCo Warp; MJX on the CPU is never faster than MuJoCo's own CPU threads (measured on the
2-core machine), so without a GPU "auto" is the CPU engine. Nothing here starts JAX unless MJX
is the estimate's choice (then JAX is asked whether it sees a GPU).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import time
from typing import Any

import mujoco
import numpy as np

from simloader import observe, sharding

# threads of the CPU engine reach this fraction of (cores x one thread's rate), as delivered
# (fitted: 0.34-0.49 for the humanoid on 16 cores, 0.42 for the cart-pole on 2)
CPU_EFFICIENCY = 0.4
# per GPU engine and contacts (True/False): (floor, cost) of one step of a batch, each as
# (seconds, multiple of the model's single-core mj_step time); fitted to simloader's delivered
# throughput on an H200 (benchmarks/results/auto_choice-h200-2026-11-26.md: cart-pole and
# humanoid at 64, 1024 and 8192 trajectories). MuJoCo Warp's floor is its graph's kernel
# launches (about 0.24 ms a step for the cart-pole, 0.52 ms for the humanoid); MJX's fused
# XLA step is cheaper without contacts and much dearer with them.
GPU_RULE = {
    "warp": {False: ((212e-6, 15.5), (0.0, 1 / 167)), True: ((212e-6, 15.5), (0.0, 1 / 199))},
    "mjx": {False: ((200e-6, 0.0), (0.0, 1 / 300)), True: ((0.0, 115.0), (0.0, 1 / 43))},
}


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
    # by the model's saved bytes: a cache by object id would outlive the model
    buffer = np.empty(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    key = hashlib.sha256(buffer.tobytes()).hexdigest()
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


def estimate(backend: str, step_s: float, nbatch: int, contacts: bool,
             cores: int) -> float:
    """The rule's steps per second of `backend` for a batch of `nbatch` trajectories of a
    model whose single-core `mj_step` takes `step_s` seconds."""
    if backend == "cpu":
        return min(nbatch, cores) / step_s * CPU_EFFICIENCY
    (floor_s, floor_k), (cost_s, cost_k) = GPU_RULE[backend][contacts]
    per_step = floor_s + floor_k * step_s + nbatch * (cost_s + cost_k * step_s)
    return nbatch / per_step


def candidates(gpu_only: bool) -> dict[str, str]:
    """{engine: why it cannot run here, or ""} for every engine `auto` may choose."""
    from simloader.backends import _gpu_visible, mjx_installed
    from simloader.backends.warp import runtime as warp_runtime
    out = {"cpu": "the GPU engines only (impl='auto')" if gpu_only else ""}
    import torch
    out["warp"] = warp_runtime.missing() or (
        "" if torch.cuda.is_available() else
        "MuJoCo Warp on the CPU (for tests) is slower than the CPU engine")
    if not mjx_installed():
        out["mjx"] = "MJX is not installed (pip install 'simloader[mjx]')"
    elif not (_gpu_visible() and _jax_gpu_plugin()):
        out["mjx"] = "JAX has no GPU here (MJX on the CPU is slower than the CPU engine)"
    else:
        out["mjx"] = ""
    return out


def _jax_gpu_plugin() -> bool:
    """Whether JAX's CUDA plugin is installed (without starting JAX)."""
    for name in ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_plugins.xla_cuda12",
                 "jax_plugins.xla_cuda13"):
        try:
            if importlib.util.find_spec(name) is not None:
                return True
        except (ImportError, ValueError):
            continue
    return False


def _jax_sees_gpu() -> bool:
    try:
        import jax
        return any(d.platform == "gpu" for d in jax.devices())
    except Exception:  # JAX without a usable platform
        return False


def choose(asked: str, gpu_only: bool, probe: Any) -> Choice:
    """The engine for `asked` (a name, or "auto"), and why.

    Args:
      asked: "cpu", "mjx", "warp" or "auto".
      gpu_only: the older `impl="auto"`: only the GPU engines may be chosen.
      probe: what the rule looks at: `model` (the base MjModel), `nbatch`, `observations`,
        `policy`.
    """
    if asked != "auto":
        return Choice(asked, "asked")
    can = candidates(gpu_only)
    cameras = any(isinstance(o, observe.CameraImage) for o in probe.observations)
    if cameras:
        can["mjx"] = can["mjx"] or "MJX does not render cameras"
    if probe.policy is not None and not can["warp"]:
        # a policy between steps: MJX dispatches a jitted step per call and waits on the
        # host, MuJoCo Warp replays one captured CUDA graph (bench_policy_mjx results)
        can["mjx"] = can["mjx"] or "a policy in the loop runs faster on MuJoCo Warp"
    running = [name for name, why in can.items() if not why]
    if not running:  # only with gpu_only: say what is missing
        raise ValueError(f"backend: no GPU engine can run here ({can['warp']}; {can['mjx']}); "
                         f"use backend='cpu'")
    if running == ["cpu"]:
        return Choice("cpu", f"auto: the only engine that runs here (warp: {can['warp']}; "
                             f"mjx: {can['mjx']})")
    contacts = has_contacts(probe.model)
    step_s = cpu_step_seconds(probe.model)
    cores = sharding.available_cpus()
    rates = {name: estimate(name, step_s, probe.nbatch, contacts, cores) for name in running}
    if cameras and "warp" in rates and "cpu" in rates:
        # rendering dominates a camera batch: MuJoCo Warp renders every world in one launch,
        # the CPU engine one image at a time per thread
        rates["warp"] = max(rates["warp"], rates["cpu"] * 2)
    order = sorted(rates, key=rates.get, reverse=True)
    best = order[0]
    if best == "mjx" and not _jax_sees_gpu():
        order.remove("mjx")
        best = order[0]
    said = ", ".join(f"{name} ~{rates[name] / 1e6:.2g}M" for name in sorted(rates, key=rates.get,
                                                                           reverse=True))
    return Choice(best, f"auto: estimated steps/s for nbatch={probe.nbatch} on {cores} cores "
                        f"and this GPU: {said} (rule in simloader/backends/auto.py)")
