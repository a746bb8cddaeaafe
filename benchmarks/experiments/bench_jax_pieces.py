"""The JAX open loop's per-step work, piece by piece, next to the raw scan.

Where do simloader's MJX-JAX batches lose time against a raw `jit(scan(vmap(mjx.step)))`? One
process, one workload at a time, every row timed alternately (medians of `--repeats`), each a
compiled batch function called back to back and blocked on its last batch:

  raw                  `bench.RawMjx`: uniform controls drawn inside, state and sensors
                       recorded batch-major (what `bench_mjx.py` compares against)
  raw + row check      the same, with a per-row finiteness check and restart after each step
  simloader function   the dataset's own compiled batch function (no torch hand-off)
  - step check         ... without the divergence check and restart after each step
  - frame check        ... without the finiteness check of recorded frames
  - clamp              ... without MuJoCo's clamp of the controls and the bad-control flag
  - set_state          ... with `d.replace(ctrl=u)` instead of `mjx.set_state(control_spec)`
  simloader delivered  batches as a user gets them (`next(iter(ds))`, torch tensors)

The removed pieces are correctness (a diverged trajectory must be flagged and restarted), so
the rows without them only say what each costs.

    python benchmarks/experiments/bench_jax_pieces.py --quick
    python benchmarks/experiments/bench_jax_pieces.py --save --results-dir $OUT  # on the GPU machine
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import contextlib  # noqa: E402
import copy  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402
from unittest import mock  # noqa: E402

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
import simloader  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("cartpole", 8192, 1000), common.Workload("humanoid", 4096, 200)]
QUICK = [common.Workload("cartpole", 64, 50)]
TARGET = 0.97


def _no_step_check(pieces, m, d):
    import jax.numpy as jnp
    return d, jnp.zeros(d.qpos.shape[0], bool)


def _no_frame_check(pieces, frame):
    return None


def _ctrl_only(pieces, m, d, u):
    from simloader.backends.mjx.runtime import mjx
    return mjx.step(m, d.replace(ctrl=u))


def _no_clamp() -> Any:
    import jax.numpy as jnp
    from simloader.backends.mjx import program
    return mock.patch.multiple(
        program.controls,
        clamp_applied=lambda control, low, high, xp: control,
        bad_controls=lambda control: jnp.zeros(control.shape[0], bool))


class Function(bench.RawBaseline):
    """A variant of the dataset's batch function, compiled, called on batch `index`'s
    arguments back to back."""

    def __init__(self, backend: Any, w: common.Workload, methods: dict[str, Callable],
                 patch: Any = None):
        import jax
        from simloader.backends.mjx import program
        self.w = w
        pieces = copy.copy(backend.program.pieces)
        for name, method in methods.items():
            setattr(pieces, name, method.__get__(pieces))
        self.args = backend.batch_args(0)
        with patch or contextlib.nullcontext(), jax.default_matmul_precision("float32"):
            self.fn = jax.jit(program.batch_function(pieces)).lower(*self.args).compile()

    def __call__(self) -> Any:
        import jax
        return jax.block_until_ready(self.fn(*self.args))


def measures(model: Any, w: common.Workload, seed: int) -> dict[str, Any]:
    ds = simloader.SimDataset(model, backend="mjx", nbatch=w.nbatch, nstep=w.nstep,
                              control=simloader.controls.Uniform(), seed=seed,
                              compilation_cache=False)
    backend = ds.make_backend()
    out: dict[str, Any] = {
        "raw": bench.RawMjx(model, w, seed),
        "raw + row check": bench.RawMjx(model, w, seed, check=True),
        "simloader function": Function(backend, w, {}),
        "- step check": Function(backend, w, {"restart_unstable": _no_step_check}),
        "- frame check": Function(backend, w, {"finite": _no_frame_check}),
        "- clamp": Function(backend, w, {}, patch=_no_clamp()),
        "- set_state": Function(backend, w, {"step": _ctrl_only}),
        "simloader delivered": bench.SimloaderMeasure(model, w, "mjx", seed,
                                                      compilation_cache=False),
    }
    backend.close()
    return out


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    args = common.parse(p)
    import jax
    jax.config.update("jax_enable_compilation_cache", False)  # compile here, not from a cache
    sections = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        start = time.perf_counter()
        rows = measures(model, w, args.seed)
        built = time.perf_counter() - start
        nbatches = common.batches_for(args, rows["raw"].batch_s)
        s_per_step = bench.interleave({name: (lambda m=m: m.measure(nbatches))
                                       for name, m in rows.items()}, args.repeats, desc=str(w))
        raw = s_per_step["raw"]
        table = bench.markdown_table(
            ["method", "steps/s", "ns/step", "/ raw", "/ simloader function"],
            [[name, bench.rate(1 / s), bench.ns(s), f"{raw / s:.3f}",
              f"{s_per_step['simloader function'] / s:.3f}"]
             for name, s in s_per_step.items()])
        verdict = s_per_step["simloader delivered"]
        sections.append(f"## {w} on {jax.devices()[0].device_kind}\n\n{table}\n\n"
                        f"simloader delivered / raw: {raw / verdict:.3f} (target {TARGET}); "
                        f"{nbatches} batches per repetition, {args.repeats} repetitions; "
                        f"built and compiled in {built:.0f} s")
    common.report(args, "bench_jax_pieces", "The JAX open loop, piece by piece", sections)


if __name__ == "__main__":
    main()
