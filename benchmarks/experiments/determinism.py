"""Run-to-run determinism of the MJX backend: one configuration streamed in fresh processes.

Every workload streams `--batches` batches with the same seed (controls drawn uniformly within
`ctrlrange` inside the jitted step, perturbed initial states) in `--runs` fresh processes, once
with XLA's default settings and once with `XLA_FLAGS=--xla_gpu_deterministic_ops=true` (XLA's
flag for run-to-run determinism on GPUs: deterministic scatters and reductions, slower). For each
output the table gives the largest absolute difference from the first run over all batches
(0: bit-identical), how many runs were bit-identical to the first, and the first step at which a
run differed; a second table gives what the flag costs (compilation, seconds per batch).

The runs of a setting share a new persistent compilation cache, as processes share simloader's
default cache: the first run compiles and the others load its executable. `--no-cache` makes
every run compile (GPU autotuning may then pick other kernels from run to run).

    python benchmarks/experiments/determinism.py --quick              # CPU JAX, small sizes
    python benchmarks/experiments/determinism.py --save --results-dir $OUT  # on the GPU machine
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from typing import Any, Optional

import numpy as np

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
import simloader  # noqa: E402

DEFAULT = [common.Workload("cartpole", 4096, 200), common.Workload("humanoid", 4096, 100)]
QUICK = [common.Workload("cartpole", 64, 20)]
# XLA_FLAGS of each setting (appended to any the caller set)
SETTINGS = {"default": "", "deterministic ops": "--xla_gpu_deterministic_ops=true"}
OUTPUTS = ("state", "sensordata", "control", "initial_state", "diverged")
STEPPED = ("state", "sensordata", "control")  # (nbatch, nstep, ...): a first differing step


def child(args: argparse.Namespace) -> None:
    """In a fresh process: saves the batches of one workload to `args.child` (npz) and prints
    the dataset's statistics as JSON."""
    import jax
    w = args.workloads[0]
    ds = simloader.SimDataset(
        common.load_model(w.name, args.model_dir), backend="mjx", nbatch=w.nbatch,
        nstep=w.nstep, control=simloader.controls.Uniform(),
        initial_state=simloader.initial.Perturbed(), seed=args.seed, num_batches=args.batches,
        compilation_cache=args.cache_dir or False)
    arrays, held = {}, []  # held: when each batch was in hand (on the host)
    for i, batch in enumerate(ds):
        arrays.update({f"{i}/{key}": batch[key].cpu().numpy() for key in OUTPUTS})
        held.append(time.perf_counter())
    np.savez(args.child, **arrays)
    # the first batch pays for the compilation (reported apart)
    steady = (held[-1] - held[0]) / (len(held) - 1) if len(held) > 1 else None
    print(json.dumps({"compile_s": ds.stats["compile_s"], "batch_s": steady,
                      "device": jax.devices()[0].device_kind}))


def difference(reference: Any, other: Any, batches: int) -> dict[str, tuple[float, Optional[tuple]]]:
    """{output: (largest |other - reference|, first (batch, step) where they differ or None)}
    over all batches of two saved runs; NaN where both hold NaN counts as equal."""
    out = {}
    for key in OUTPUTS:
        largest, first = 0.0, None
        for b in range(batches):
            x = reference[f"{b}/{key}"].astype(np.float64)
            y = other[f"{b}/{key}"].astype(np.float64)
            differ = (x != y) & ~(np.isnan(x) & np.isnan(y))
            if not differ.any():
                continue
            with np.errstate(invalid="ignore"):
                gap = np.abs(x - y)[differ]
            largest = max(largest, float(np.nan_to_num(gap, nan=np.inf).max()))
            if first is None:
                step = int(np.flatnonzero(differ.any(axis=(0, 2)))[0]) if key in STEPPED else None
                first = (b, step)
        out[key] = (largest, first)
    return out


def where(first: Optional[tuple]) -> str:
    if first is None:
        return "-"
    batch, step = first
    return f"batch {batch}" + ("" if step is None else f", step {step}")


def measure(w: common.Workload, flags: str, args: argparse.Namespace,
            work: str) -> tuple[list[list[str]], Optional[list[str]]]:
    """Runs `w` in `args.runs` fresh processes with these extra XLA flags; rows of the
    difference table and the row of the cost table (None if a run failed)."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {flags}".strip()
    cache = None if args.no_cache else os.path.join(work, "jax-cache")
    if args.no_cache:  # leave no cache JAX might be configured with either
        env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
    setting = flags or "(none)"
    results, files = [], []
    for run in range(args.runs):
        path = os.path.join(work, f"run{run}.npz")
        command = [sys.executable, __file__, "--child", path, "--workloads", str(w),
                   "--model-dir", str(common.model_dir(args.model_dir)), "--seed",
                   str(args.seed), "--batches", str(args.batches)]
        if cache:
            command += ["--cache-dir", cache]
        result = common.run_child(command, f"run {run + 1} of {w} with XLA_FLAGS {setting}", env)
        if result is None:
            return [[w.name, f"{w.nbatch} x {w.nstep}", setting, "failed", "-", "-", "-"]], None
        results.append(result)
        files.append(path)
    reference = np.load(files[0])
    diffs = [difference(reference, np.load(f), args.batches) for f in files[1:]]
    rows = []
    for key in OUTPUTS:
        largest = max((d[key][0] for d in diffs), default=0.0)
        firsts = [d[key][1] for d in diffs if d[key][1] is not None]
        identical = sum(d[key][1] is None for d in diffs)
        rows.append([w.name, f"{w.nbatch} x {w.nstep}", setting, key, f"{largest:.3g}",
                     f"{identical}/{len(diffs)}", where(min(firsts) if firsts else None)])
    cost = [w.name, f"{w.nbatch} x {w.nstep}", setting, results[0]["device"],
            f"{results[0]['compile_s']:.1f}",
            f"{statistics.median(r['compile_s'] for r in results[1:]):.1f}"
            if len(results) > 1 else "-",
            "-" if args.batches < 2 else
            f"{statistics.median(r['batch_s'] for r in results):.4f}"]
    return rows, cost


DIFF_HEADERS = ["workload", "nbatch x nstep", "XLA_FLAGS", "output",
                "largest abs. difference from run 1", "runs bit-identical to run 1",
                "first difference"]
COST_HEADERS = ["workload", "nbatch x nstep", "XLA_FLAGS", "device", "compile s (run 1)",
                "compile s (later runs, median)",
                "s per batch after the first, to host (median)"]


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, repeats=False)
    p.add_argument("--runs", type=int, default=3, help="fresh processes per workload and setting")
    p.add_argument("--batches", type=int, default=3, help="batches each run streams")
    p.add_argument("--no-cache", action="store_true",
                   help="every run compiles (no persistent compilation cache)")
    # child mode: one run, saved to this file
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--cache-dir", help=argparse.SUPPRESS)
    args = common.parse(p)
    if args.runs < 2 or args.batches < 1:
        p.error(f"--runs must be >= 2 and --batches >= 1, got {args.runs} and {args.batches}")
    if args.child:
        return child(args)

    table, costs = [], []
    jobs = [(w, flags) for flags in SETTINGS.values() for w in common.workloads(args, DEFAULT,
                                                                               QUICK)]
    for w, flags in common.progress(jobs, desc="workloads x settings"):
        # each job's runs (GBs for large workloads) and cache are deleted after it
        with tempfile.TemporaryDirectory(prefix="simloader-determinism-") as work:
            rows, cost = measure(w, flags, args, work)
        table += rows
        if cost is not None:
            costs.append(cost)
    cache = ("every run compiled (no persistent cache)" if args.no_cache else
             "the runs of a setting share a new persistent compilation cache (run 1 compiles, "
             "the others load its executable)")
    sections = [
        f"The same configuration (seed {args.seed}, uniform random controls, perturbed initial "
        f"states, {args.batches} batches) in {args.runs} fresh processes per workload and "
        f"XLA_FLAGS setting; {cache}. Differences are from run 1, over all batches, in the "
        f"delivered float32 values; `diverged` differs by 1 where a flag differs.",
        common.markdown_table(DIFF_HEADERS, table),
        "What the setting costs:\n\n" + common.markdown_table(COST_HEADERS, costs),
    ]
    if args.save:
        common.save(args, "determinism", "MJX run-to-run determinism", sections)
    print("\n\n".join(sections))


if __name__ == "__main__":
    main()
