"""The CPU engine as the registry sees it (`backend="cpu"`): light, imports nothing heavy."""

from __future__ import annotations

from typing import Any, Optional

from simloader.backends.contract import Engine, EngineEntry, Job

# its threads reach this fraction of (cores x one thread's rate), as delivered (fitted:
# 0.34-0.49 for the humanoid on 16 cores, 0.34-0.46 for the cart-pole on 2;
# benchmarks/results/auto_choice-*.md)
EFFICIENCY = 0.35
# a policy between steps (a torch call per step on the host): the closed loop's share of the
# open loop's rate (0.25 for the cart-pole, 0.5 for the humanoid on 2 cores;
# bench_policy_rollout-every-step-checked-2core-2026-11-26.md)
POLICY = 0.3
# cameras: one mujoco.Renderer per thread; the rendered batch's share of the plain one
# (cart-pole, 64x64 RGB every step, 2 cores: auto_choice-2core-2026-11-26.md)
CAMERAS = 0.05


class CpuEngine(EngineEntry):
    """MuJoCo's native multithreaded CPU simulation (`mujoco.batch`), bit for bit
    `mujoco.rollout`."""

    name = "cpu"
    options = ()
    forks_safely = True  # MuJoCo's threads start in the process that iterates

    def estimate(self, job: Job) -> Optional[float]:
        if job.cameras:
            from simloader import render
            try:
                render.gl_platform()
            except (RuntimeError, ValueError):
                return None  # no OpenGL here: it cannot render
        rate = min(job.nbatch, job.cores) / job.step_s * EFFICIENCY
        return rate * (POLICY if job.policy else 1.0) * (CAMERAS if job.cameras else 1.0)

    def refuses_sim_device(self) -> Optional[str]:
        return ("the CPU engine simulates on the CPU's threads (nthread=); sim_device is for "
                "the GPU engines (backend='mjx' or 'warp')")

    def refuses_determinism(self, model: Any) -> Optional[str]:
        return None  # each trajectory on one thread, in MuJoCo's fixed order: always

    def check_sizes(self, sizes: Any) -> None:
        from simloader.backends.cpu import options
        options.check_sizes(sizes)

    def check_options(self, config: Any, options: dict[str, Any], reason: str) -> Any:
        from simloader.backends.cpu import options as cpu_options
        return cpu_options.check_options(config, options, reason)

    def stored_renderer(self, model: Any, images: Any, device: Any,
                        randomized: bool) -> Any:
        """`mujoco.Renderer`s in each thread that reads (the engine's own renderer)."""
        if device is not None and str(device) != "cpu":
            raise ValueError(f"device: backend='cpu' renders on the host and delivers on "
                             f"'cpu', got {device!r}")
        from simloader import render
        return render.StoredFrames(model, images)

    def create(self, config: Any, shard: Any, stats: Any) -> Any:
        from simloader.backends.cpu.backend import CpuBackend
        return CpuBackend(config, shard, stats)


# annotated: a type checker holds the entry to the protocol (tests/test_engines.py runs mypy)
ENGINE: Engine = CpuEngine()
