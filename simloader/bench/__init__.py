"""simloader next to the raw simulators it wraps: `simloader bench` and `benchmarks/`.

- `raw`: the raw baselines (a Python loop, `mujoco.rollout`, a jitted MJX scan, a captured
  MuJoCo Warp graph), which depend on MuJoCo, JAX and MuJoCo Warp alone;
- `timing`: alternating repetitions, medians, a delivered stream timed with tensors in hand;
- `compare`: `simloader bench MODEL`, one model and size on every engine here;
- `suite`: `simloader bench run`, the named workloads of `workloads` held to their targets,
  results as JSON lines (`results`), rendered by `simloader bench report`.

Imported only by the commands that use it (it imports torch and MuJoCo); the names of `raw`,
`timing` and `compare` are re-exported here for the benchmark scripts.
"""

from simloader.bench.compare import (HEADERS, bar_plot, compare, markdown_table, method_rows,
                                     ns, rate, ratio)
from simloader.bench.raw import (PYTHON, RAW_MJX, RAW_OF, RAW_ROLLOUT, RAW_WARP, SIMLOADER_MJX,
                                 SIMLOADER_ROLLOUT, SIMLOADER_WARP, STEP_READS, RawBaseline,
                                 RawMjx, RawRenderers, RawWarp, StatePolicy, Workload,
                                 ctrl_bounds, default_state, mlp, python_loop, raw_baseline,
                                 raw_rollout)
from simloader.bench.timing import (SimloaderMeasure, Stream, batches_for, cpu_count,
                                    device_name, drain, interleave, progress, read_frames, sync,
                                    time_stream)

__all__ = [
    "HEADERS", "PYTHON", "RAW_MJX", "RAW_OF", "RAW_ROLLOUT", "RAW_WARP", "SIMLOADER_MJX",
    "SIMLOADER_ROLLOUT", "SIMLOADER_WARP", "STEP_READS", "RawBaseline", "RawMjx",
    "RawRenderers", "RawWarp", "SimloaderMeasure", "StatePolicy", "Stream", "Workload",
    "bar_plot", "batches_for", "compare", "cpu_count", "ctrl_bounds", "default_state",
    "device_name", "drain", "interleave", "markdown_table", "method_rows", "mlp", "ns",
    "progress", "python_loop",
    "rate", "ratio", "raw_baseline", "raw_rollout", "read_frames", "sync", "time_stream",
]
