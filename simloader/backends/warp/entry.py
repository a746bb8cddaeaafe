"""The Warp engine as the registry sees it (`backend="warp"`): light; neither Warp nor CUDA
is started by these checks."""

from __future__ import annotations

from typing import Any, Optional

from simloader.backends import gpu_rule
from simloader.backends.contract import Engine, EngineEntry, Job

# (floor, cost) of one step of a batch, fitted on an H200 to simloader's delivered steps/s
# (archive/auto_choice-h200-2026-11-26.md): the graph's kernel launches, about 0.24 ms a step for the
# cart-pole and 0.52 ms for the humanoid, then a small cost per trajectory
RULE = {False: ((212e-6, 15.5), (0.0, 1 / 167)), True: ((212e-6, 15.5), (0.0, 1 / 199))}
# a torch policy between steps inside the captured graph: 0.78 of the open loop for the
# cart-pole, 1.0 for the humanoid (bench_policy_mjx-every-step-checked-h200-2026-11-26.md)
POLICY = 0.8
# seconds to the first batch on a machine's first run: MuJoCo Warp compiles its kernels (21 s
# for the humanoid, 38 s for the cart-pole on the H200; cached afterwards, a few seconds)
STARTUP = 20.0
# cameras: MuJoCo Warp renders every world in one launch; the rendered batch's share of the
# plain one (cart-pole, one 64x64 RGB camera every step: 0.09-0.31, auto_choice-h200)
CAMERAS = 0.1


class WarpEngine(EngineEntry):
    """MuJoCo Warp driven from torch with CUDA graphs; no JAX."""

    name = "warp"
    options = ("naconmax", "njmax")
    # overflow: trajectories that lost contacts or constraint rows to the buffer sizes (the
    # batch's `overflow` flags them); solver_limit: trajectories whose constraint solver
    # stopped at its iteration limit in a batch (MuJoCo C stops there too, silently);
    # graph_captures: CUDA graphs captured, one per dataset and device, at its first batch;
    # compile_s: seconds building the engine there (MuJoCo Warp's model and data on the
    # device, its kernels and simloader's compiled or loaded, the step graph captured)
    counters = ("overflow", "solver_limit", "graph_captures", "compile_s")

    def missing(self) -> Optional[str]:
        import torch
        from simloader.backends.warp import runtime
        why = runtime.missing()
        if why is None and not torch.cuda.is_available():
            # SIMLOADER_WARP_ON_CPU runs it on Warp's CPU device for the tests: never for auto
            return "MuJoCo Warp on the CPU (for tests) is slower than the CPU engine"
        return why

    def estimate(self, job: Job) -> Optional[float]:
        rate = gpu_rule.steps_per_second(job, RULE)
        return rate * (POLICY if job.policy else 1.0) * (CAMERAS if job.cameras else 1.0)

    def startup_s(self, job: Job) -> float:
        """A first run's: MuJoCo Warp's kernels compiled, the engine built, its graph
        captured (later runs load the kernels in seconds: `simloader warmup`)."""
        return STARTUP

    def refuses_sim_device(self) -> Optional[str]:
        return None  # its GPUs: each part of a batch on its own

    def refuses_model(self, model: Any) -> Optional[str]:
        """State the Warp engine does not simulate, and what MuJoCo Warp's `put_model`
        refuses (its arrays made on Warp's CPU device: no kernel compiled)."""
        from simloader.backends.warp import runtime
        if runtime.missing() is not None:
            return None  # `missing` says why it cannot run at all
        from simloader.backends.warp import model_arrays, options as warp_options
        try:
            warp_options.check_simulated("model", model)
            model_arrays.put("model", model)
        except ValueError as e:
            return str(e).removeprefix("model: ")
        return None

    def refuses_determinism(self, model: Any) -> Optional[str]:
        """Only models whose steps no GPU atomics can reorder (`warp/determinism.py`)."""
        from simloader.backends.warp import determinism
        return determinism.refusal(model)

    def check_options(self, config: Any, options: dict[str, Any], reason: str) -> Any:
        from simloader.backends.warp import options as warp_options
        return warp_options.check_options(config, options, reason)

    def stored_renderer(self, model: Any, images: Any, device: Any,
                        randomized: bool) -> Any:
        """MuJoCo Warp's renderer on a GPU, every frame of a read batch one world."""
        from simloader.backends.warp.stored import StoredRenderer
        return StoredRenderer(model, images, device, randomized)

    def create(self, config: Any, shard: Any, stats: Any) -> Any:
        from simloader.backends.warp.backend import WarpBackend
        return WarpBackend(config, shard, stats, config.options)


# annotated: a type checker holds the entry to the protocol (tests/test_engines.py runs mypy)
ENGINE: Engine = WarpEngine()
