"""simloader's MJX backend next to a raw jitted `scan` over `vmap(mjx.step)` doing the same work.

Both simulate `nbatch` trajectories of `nstep` steps from the model's default state in float32,
draw the controls uniformly within `ctrlrange` with `jax.random` inside the jitted function for
every batch, and record the state (time, qpos, qvel, act) and the sensors after every step,
batch-major. simloader is timed as delivered: torch tensors in hand on the device, over
`--batches` batches (more if they take under `--min-seconds`) after a warm-up batch,
`torch.cuda.synchronize()` after each; raw as as many back-to-back calls, each blocked with
`jax.block_until_ready`. They run alternately in one process; medians of `--repeats`
repetitions. A single-environment Python `mj_step` loop gives the speed-up column; `--cpu` adds
raw `mujoco.rollout` and simloader's rollout backend on all cores (bench_rollout.py's code).

`--backend` picks simloader's GPU engine (`mjx`, `warp` or `auto`); the raw baseline runs the
engine simloader resolved. On
`warp` that is simloader's Warp engine, the public `mujoco_warp` from torch (not MJX's vendored
Warp through JAX): the raw rows are `simloader.bench.RawWarp`, one captured step graph replayed
with the same work (controls in, state and sensors out every step) and with no controls at all
(the upper bound, MuJoCo Warp's own `testspeed` setting), with simloader's buffer sizes.
benchmarks/bench_warp.py has more Warp rows (policy, pixels, startup).

Compilation is reported apart: in this process (persistent cache off), and as the time to the
first batch of a fresh process with empty persistent caches (cold: JAX's compilation cache and,
on Warp, its kernel cache) and of a second process reusing them (cached).

    python benchmarks/bench_mjx.py --quick
    python benchmarks/bench_mjx.py --save --results-dir $OUT          # on the GPU machine
    python benchmarks/bench_mjx.py --workloads humanoid:4096x200 humanoid:16384x200 --cpu
    python benchmarks/bench_mjx.py --backend warp --workloads humanoid:8192x200 --save
"""

from __future__ import annotations

import os

# torch shares the GPU (DLPack views, training); JAX must not take 75% of it up front
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any, Optional  # noqa: E402

import mujoco  # noqa: E402

import bench_rollout  # noqa: E402
import common  # noqa: E402
import simloader  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("cartpole", n, 1000) for n in (1024, 8192, 65536)] + \
    [common.Workload("humanoid", n, 200) for n in (4096, 16384)]
QUICK = [common.Workload("cartpole", 64, 20)]
TARGET = 0.97  # simloader / raw MJX throughput (performance.md)



def jax_device() -> str:
    import jax
    return jax.devices()[0].device_kind


def output_gb(model: mujoco.MjModel, w: common.Workload) -> float:
    """Size of one batch's float32 state, sensordata and control."""
    nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return w.steps * (nstate + model.nsensordata + model.nu) * 4 / 1e9


RawMjx = bench.RawMjx  # the package's baseline of backend="mjx" (it backs `simloader bench` too)


def simloader_dataset(model: mujoco.MjModel, w: common.Workload, seed: int,
                      cache: Any, backend: str) -> simloader.SimDataset:
    """The dataset measured; `cache`: its `compilation_cache` option (False: JAX's setting;
    for MJX only)."""
    options = {"compilation_cache": cache} if backend == "mjx" else {}
    return simloader.SimDataset(model, backend=backend, nbatch=w.nbatch, nstep=w.nstep,
                                control=simloader.controls.Uniform(), seed=seed, **options)


class SimloaderMjx(bench.SimloaderMeasure):
    """simloader's MJX backend, warmed up by one pass (which compiles), then measured."""

    def __init__(self, model: mujoco.MjModel, w: common.Workload, seed: int, backend: str):
        import torch
        # compilation_cache=False: JAX's setting, which main() turns off in this process
        options = {"compilation_cache": False} if backend == "mjx" else {}
        super().__init__(model, w, backend, seed, **options)
        self.options = self.ds.config.options  # the engine's resolved options, buffer sizes
        if torch.cuda.is_available() and self.device.type != "cuda":
            raise RuntimeError(f"simloader mjx delivered on {self.device}, not on the GPU")

    def recompiled(self) -> bool:
        """Whether later iterators compiled again (each pass should reuse the first's)."""
        return self.ds.stats.get("compile_s", 0.0) > 1.5 * self.compile_s + 0.5


def first_batch_child(args: argparse.Namespace) -> None:
    """In a fresh process: seconds from `SimDataset(...)` to the first batch, as JSON."""
    import jax
    w = args.workloads[0]
    model = common.load_model(w.name, args.model_dir)
    start = time.perf_counter()
    ds = simloader_dataset(model, w, args.seed, cache=args.cache_dir, backend=args.backend)
    common.time_stream(ds, 0)
    print(json.dumps({"first_batch_s": time.perf_counter() - start,
                      "compile_s": ds.stats.get("compile_s", 0.0),
                      "cache_dir": jax.config.jax_compilation_cache_dir}))


def cold_and_cached(w: common.Workload, args: argparse.Namespace) -> list[str]:
    """Time to first batch of two fresh processes sharing a new persistent cache."""
    with tempfile.TemporaryDirectory(prefix="simloader-jax-cache-") as cache, \
            tempfile.TemporaryDirectory(prefix="simloader-warp-cache-") as warp_cache:
        command = [sys.executable, __file__, "--first-batch", "--cache-dir", cache,
                   "--workloads", str(w), "--model-dir", str(common.model_dir(args.model_dir)),
                   "--seed", str(args.seed), "--backend", args.backend]
        env = dict(os.environ, WARP_CACHE_PATH=warp_cache)
        row = [w.name, f"{w.nbatch} x {w.nstep}"]
        for run in ("cold", "cached"):
            start = time.perf_counter()
            result = common.run_child(command, f"{run} first batch of {w}", env=env)
            wall = time.perf_counter() - start
            if result is None:
                return row + ["failed"] * (len(COMPILE_HEADERS) - len(row))
            if result["cache_dir"] != cache:
                print(f"warning: the child used the compilation cache {result['cache_dir']!r}, "
                      f"not {cache!r}", file=sys.stderr)
            row += [f"{result['first_batch_s']:.2f}", f"{result['compile_s']:.2f}",
                    f"{wall:.2f}"]
        return row


COMPILE_HEADERS = ["workload", "nbatch x nstep", "cold: first batch s", "cold: compile_s",
                   "cold: process s", "cached: first batch s", "cached: compile_s",
                   "cached: process s"]


def try_simloader(model: mujoco.MjModel, w: common.Workload, seed: int,
                  backend: str) -> tuple[Optional[SimloaderMjx], str]:
    """simloader's GPU engine measure, or None and why (it may be missing or failing)."""
    try:
        return SimloaderMjx(model, w, seed, backend), ""
    except Exception as e:  # report and go on with the raw numbers
        traceback.print_exc()
        return None, f"{type(e).__name__}: {e}".splitlines()[0][:200]


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--backend", choices=("mjx", "warp", "auto"), default="mjx",
                   help="simloader's GPU engine (raw runs the engine it resolved)")
    p.add_argument("--cpu", action="store_true",
                   help="also raw mujoco.rollout and simloader's rollout backend on all cores")
    p.add_argument("--no-compile", action="store_true",
                   help="skip the cold/cached time to first batch (two fresh processes each)")
    p.add_argument("--compile-workloads", nargs="+", type=common.parse_workload,
                   help="workloads of the cold/cached measurement (default: the smallest "
                        "workload of each model)")
    # child mode: the time to first batch of a fresh process with this compilation cache
    p.add_argument("--first-batch", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--cache-dir", help=argparse.SUPPRESS)
    args = common.parse(p)
    if args.first_batch:
        return first_batch_child(args)
    import jax
    jax.config.update("jax_enable_compilation_cache", False)  # in-process compiles are cold
    run = common.workloads(args, DEFAULT, QUICK)

    compile_table = []
    if not args.no_compile:
        smallest = {}
        for w in run:
            if w.name not in smallest or w.steps < smallest[w.name].steps:
                smallest[w.name] = w
        for w in common.progress(args.compile_workloads or list(smallest.values()),
                                 desc="cold/cached first batch"):
            compile_table.append(cold_and_cached(w, args))

    table, notes, plot, counts = [], [], {}, []
    gpu = jax_device()
    for w in run:
        model = common.load_model(w.name, args.model_dir)
        sim, why = try_simloader(model, w, args.seed, args.backend)
        impl = sim.ds.config.backend if sim is not None else (
            "mjx" if args.backend == "auto" else args.backend)
        SIMLOADER = f"simloader {impl}"
        if impl == "warp":
            # simloader's Warp engine is mujoco_warp from torch: its raw loop, not MJX's Warp,
            # with MuJoCo Warp's buffer sizes as simloader resolved them
            sizes = (sim.options.naconmax, sim.options.njmax) if sim else (None, None)
            RAW, raw = bench.RAW_WARP, bench.RawWarp(model, w, args.seed, sizes)
        else:
            RAW, raw = "raw MJX vmap+scan", RawMjx(model, w, args.seed)
        nbatches = common.batches_for(args, raw.batch_s)
        counts.append(f"{nbatches} for {w}")
        measures: dict[str, Callable[[], float]] = {RAW: lambda: raw.measure(nbatches)}
        runs_on = {RAW: gpu, SIMLOADER: gpu, bench_rollout.PYTHON: "1 core"}
        bare = None
        if impl == "warp":
            BARE = "raw MuJoCo Warp graph, no controls"
            bare = bench.RawWarp(model, w, args.seed, sizes, same_work=False)
            measures[BARE] = lambda: bare.measure(nbatches)
            runs_on[BARE] = gpu
            if sim is not None:
                notes.append(f"{w}: simloader ran {sim.ds.config.backend} "
                             f"({sim.ds.config.backend_reason}), "
                             f"naconmax={sim.options.naconmax}, njmax={sim.options.njmax}")
        if sim is not None:
            measures[SIMLOADER] = lambda: sim.measure(nbatches)
            differ = {k: (sim.shapes[k], v) for k, v in raw.shapes.items() if sim.shapes[k] != v}
            if differ:
                notes.append(f"{w}: not the same work, (simloader, raw) shapes {differ}")
        else:
            notes.append(f"{w}: simloader mjx unavailable ({why})")
        measures[bench_rollout.PYTHON] = bench_rollout.python_loop(
            model, w.nstep, args.python_steps, args.seed)
        if args.cpu:
            cpu, cpu_runs_on, cpu_batches = bench_rollout.cpu_measures(model, w, args)
            del cpu[bench_rollout.PYTHON]
            measures.update(cpu)
            runs_on.update(cpu_runs_on)
            counts.append(f"{cpu_batches} for {w} on the CPU")
        results = common.interleave(measures, args.repeats, desc=str(w))
        if sim is not None and sim.recompiled():
            notes.append(f"{w}: simloader compiled again for later iterators "
                         f"(compile_s {sim.ds.stats['compile_s']:.1f} s in total)")
        compiled = {RAW: raw, SIMLOADER: sim}
        if bare is not None:
            compiled[BARE] = bare
            rate_ = results[BARE] / results.get(SIMLOADER, float("inf"))
            notes.append(f"{w}: simloader with per-step controls / raw with no controls: "
                         f"{rate_:.3f}")
        for row in common.method_rows(w, results, runs_on,
                                      {SIMLOADER: RAW, bench_rollout.SIMLOADER: bench_rollout.RAW},
                                      bench_rollout.PYTHON):
            c = compiled.get(row[2])
            table.append(row + ([f"{c.compile_s:.1f}", f"{c.first_s:.1f}"] if c else ["-", "-"])
                         + [f"{output_gb(model, w):.3g}"])
        for method in (RAW, SIMLOADER):
            if method in results:
                xs, ys = plot.setdefault(f"{method}, {w.name}", ([], []))
                xs.append(w.nbatch)
                ys.append(results[method] * 1e9)
        del raw, sim, measures, compiled, bare

    headers = common.HEADERS + ["compile s", "first batch s", "GB/batch"]
    text = common.markdown_table(headers, table)
    summary = (f"Medians of {args.repeats} alternating repetitions, each timing batches after a "
               f"warm-up ({', '.join(counts)}); float32 on {gpu}. Target: simloader throughput "
               f"/ raw >= {TARGET}. compile s / first batch s: in this process, persistent "
               f"cache off.")
    sections = [summary]
    if compile_table:
        sections.append("Time to first batch of a fresh process (simloader mjx), with an empty "
                        "persistent compilation cache (cold) and reusing it (cached); targets: "
                        "cartpole cold < 10 s, cached < 2 s, humanoid cached < 5 s.\n\n"
                        + common.markdown_table(COMPILE_HEADERS, compile_table))
    sections += notes
    sections.append(text)
    if args.save:
        figure = common.save_plot(args, "bench_mjx", plot, "nbatch (trajectories per batch)",
                                  "ns per step", f"simloader mjx vs raw MJX on {gpu}")
        if figure is not None:
            sections.insert(-1, f"![ns/step vs nbatch]({figure.name})")
        common.save(args, "bench_mjx", "simloader MJX backend vs raw MJX", sections)
    print("\n\n".join(sections))


if __name__ == "__main__":
    main()
