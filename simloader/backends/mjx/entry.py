"""MJX as the registry sees it (`backend="mjx"`): light; JAX is imported only to set its
memory before it starts, and started only to confirm that it sees a GPU."""

from __future__ import annotations

import importlib.util
from typing import Any, Optional

from simloader.backends import gpu_rule
from simloader.backends.contract import Engine, EngineEntry, Job

# (floor, cost) of one step of a batch, fitted on an H200 to simloader's delivered steps/s
# (archive/auto_choice-h200-2026-11-26.md): XLA fuses a contact-free step (about 0.2 ms a step
# whatever the batch); contacts make it much dearer per trajectory
RULE = {False: ((200e-6, 0.0), (0.0, 1 / 300)), True: ((0.0, 115.0), (0.0, 1 / 43))}
# MJX on JAX's CPU (no GPU): XLA spreads the vmapped batch over the cores; a step of the batch
# takes CPU_FLOOR + nbatch * CPU_COST[contacts] * step_s / cores, fitted on the 2-core
# machine (auto_choice-2core-*): the tiny contact-free cart-pole runs 1.2-1.4x the CPU engine's
# rate at 1024 and 8192 trajectories, the humanoid 6-7x slower than the CPU engine. At 64 the
# two are within run-to-run noise of each other (three runs: MJX 0.33-0.48M, the CPU engine
# 0.30-0.43M; MJX ahead on average)
CPU_FLOOR = 37e-6
CPU_COST = {False: 1.95, True: 12.4}
# seconds to the first batch (a cold compilation), without and with contacts
STARTUP_GPU = {False: 4.0, True: 20.0}
STARTUP_CPU = {False: 8.0, True: 45.0}
# a torch policy between jitted steps: a dispatch and a host round trip per step, about a
# tenth of the open loop (bench_policy_mjx-jax-2026-11-24.md: 1.94M against 19.2M)
POLICY = 0.1
_CUDA_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_plugins.xla_cuda12",
                 "jax_plugins.xla_cuda13")


def installed() -> bool:
    return importlib.util.find_spec("mujoco.mjx") is not None


def _found(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


class MjxEngine(EngineEntry):
    """MJX in XLA on JAX (`jit` + `vmap` + `scan`)."""

    name = "mjx"
    options = ("compilation_cache", "memory_fraction")
    # compile_s: seconds making the batch function ready (tracing, lowering, compiling, or
    # loading what earlier processes stored); compiles: one per configuration, never per
    # batch; traces: times it was traced in Python (0 when a stored program was loaded);
    # trace_s: of compile_s, tracing and lowering; programs_loaded: loaded, not traced
    counters = ("compile_s", "compiles", "traces", "trace_s", "programs_loaded")

    def missing(self) -> Optional[str]:
        if not installed():
            return "MJX is not installed (pip install 'simloader[mjx]')"
        return None

    def confirm(self) -> Optional[str]:
        """JAX started: whether it sees the GPU the estimate assumed (where one may be)."""
        if not self._gpu():
            return None
        try:
            import jax
            if any(d.platform == "gpu" for d in jax.devices()):
                return None
        except Exception:  # noqa: BLE001 - JAX without a usable platform
            pass
        return "JAX sees no GPU"

    @staticmethod
    def _gpu() -> bool:
        """Whether JAX may have a GPU here, decided without starting it."""
        from simloader.backends import gpu_visible
        return gpu_visible() and any(_found(p) for p in _CUDA_PLUGINS)

    def estimate(self, job: Job) -> Optional[float]:
        if job.cameras or job.episode_callable:
            return None  # MJX does not render; episodes end in the open loop only
        if self._gpu():
            rate = gpu_rule.steps_per_second(job, RULE)
        else:
            rate = job.nbatch / (CPU_FLOOR + job.nbatch * CPU_COST[job.contacts] * job.step_s
                                 / job.cores)
        return rate * (POLICY if job.policy else 1.0)

    def startup_s(self, job: Job) -> float:
        """Tracing and compiling the batch function the first time (kept on disk after):
        measured 4 s for the cart-pole and about 20 s for the humanoid on an H200 (16 cores),
        3-10 s and 37-54 s on JAX's CPU on the 2-core machine (auto_choice-* logs)."""
        if self._gpu():
            return STARTUP_GPU[job.contacts]
        return STARTUP_CPU[job.contacts]

    def prepare(self, options: dict[str, Any]) -> None:
        from simloader.backends import gpu_visible
        if installed() and gpu_visible():
            from simloader.backends.mjx import options as mjx_options, runtime
            runtime.configure_memory(
                mjx_options.memory_fraction(options.get("memory_fraction")))

    def refuses_sim_device(self) -> Optional[str]:
        return None  # its GPUs: each part of a batch on its own

    def refuses_model(self, model: Any) -> Optional[str]:
        """Collisions MJX does not implement (by geom pair), frictionless contacts under the
        elliptic cone, state it does not simulate (`support.refusal`)."""
        if not installed():
            return None  # `missing` says why it cannot run at all
        from simloader.backends.mjx import support
        return support.refusal(model)

    def refuses_determinism(self, model: Any) -> Optional[str]:
        """XLA's deterministic GPU ops, which `check_options` sets before JAX starts
        (1.25-1.7x slower on an H200, benchmarks/results/determinism-*): refused, saying how,
        only where JAX started without them."""
        if not installed():
            return None  # `missing` says why it cannot run at all
        from simloader.backends.mjx import runtime
        return runtime.determinism_refusal()

    def check_options(self, config: Any, options: dict[str, Any], reason: str) -> Any:
        if config.terminate is not None and config.terminate.check is not None \
                and config.policy is None:
            raise ValueError("terminate: a callable over the observations runs where the "
                             "simulation steps from Python: on MJX, the closed loop "
                             "(policy=), not the open loop's jitted scan; use policy=, "
                             "backend='cpu' or 'warp', or rules of simloader.terminate")
        from simloader.backends.mjx import options as mjx_options, runtime
        if config.deterministic:  # before anything below starts JAX
            runtime.configure_determinism()
        return mjx_options.check_options(config, options, reason)

    def create(self, config: Any, shard: Any, stats: Any) -> Any:
        from simloader.backends.mjx.backend import MjxBackend
        return MjxBackend(config, shard, stats, config.options)


# annotated: a type checker holds the entry to the protocol (tests/test_engines.py runs mypy)
ENGINE: Engine = MjxEngine()
