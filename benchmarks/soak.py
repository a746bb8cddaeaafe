"""Soak: stream many batches and watch host RSS and GPU memory stay flat.

Streams `--batches` batches (10^5 by default) from one dataset, sampling the process's resident
memory and the GPU memory in use every `--every` batches, and reports the growth after warm-up
(the first 10% of batches): the target is under 50 MB, with no recompilation after the first
batch (MJX). Prints a table and, with --save, writes it with a plot to benchmarks/results/.

    python benchmarks/soak.py --backend rollout --batches 100000
    python benchmarks/soak.py --backend mjx --batches 100000 --save
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch

import common
import simloader

GROWTH_LIMIT_MB = 50.0


def host_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def gpu_used_mb() -> float:
    """Memory in use on GPU 0 by every allocator (JAX's and torch's), from the driver."""
    if not torch.cuda.is_available():
        return float("nan")
    free, total = torch.cuda.mem_get_info()
    return (total - free) / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="rollout", choices=("rollout", "mjx"))
    parser.add_argument("--model", default="cartpole")
    parser.add_argument("--batches", type=int, default=100_000)
    parser.add_argument("--nbatch", type=int, default=64)
    parser.add_argument("--nstep", type=int, default=10)
    parser.add_argument("--every", type=int, default=0, help="sample period (default: 1%%)")
    parser.add_argument("--quick", action="store_true", help="2,000 batches")
    parser.add_argument("--save", action="store_true")
    parser.add_argument("--results-dir", default=common.REPO / "benchmarks" / "results",
                        type=common.pathlib.Path)
    parser.add_argument("--tag", default="")
    args = parser.parse_args()
    if args.quick:
        args.batches = 2000
    every = args.every or max(1, args.batches // 100)

    ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                              nstep=args.nstep, control=simloader.controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(), seed=0,
                              device="cuda" if torch.cuda.is_available() else None)
    samples = []  # (batch, seconds, rss MB, gpu MB)
    start = time.perf_counter()
    checksum = 0.0
    for i, batch in enumerate(common.progress(ds, desc=f"soak {args.backend}",
                                              total=args.batches)):
        if i % every == 0 or i == args.batches - 1:
            common.sync()
            checksum += float(batch["state"][0, -1, 1])  # touch the data
            samples.append((i, time.perf_counter() - start, host_rss_mb(), gpu_used_mb()))
        if i == args.batches - 1:
            break
    stats = ds.stats
    warm = samples[max(1, len(samples) // 10)]
    last = samples[-1]
    rss_growth, gpu_growth = last[2] - warm[2], last[3] - warm[3]
    gpu_ok = gpu_growth != gpu_growth or gpu_growth < GROWTH_LIMIT_MB  # NaN: no GPU
    rows = [
        ["batches", f"{args.batches:,}"],
        ["wall time", f"{last[1]:.0f} s"],
        ["host RSS after warm-up / at the end", f"{warm[2]:.0f} MB / {last[2]:.0f} MB"],
        ["host RSS growth after warm-up", f"{rss_growth:+.1f} MB "
                                          f"({'ok' if rss_growth < GROWTH_LIMIT_MB else 'FAIL'})"],
        ["GPU memory after warm-up / at the end", f"{warm[3]:.0f} MB / {last[3]:.0f} MB"],
        ["GPU memory growth after warm-up", f"{gpu_growth:+.1f} MB ({'ok' if gpu_ok else 'FAIL'})"],
        ["compilations (MJX: one per configuration)", str(stats["compiles"])],
        ["diverged trajectories", str(stats["diverged"])],
    ]
    table = common.markdown_table(["soak", f"{args.backend}, {args.model} {args.nbatch}x{args.nstep}"],
                                  rows)
    print(table)
    if args.save:
        name = f"soak-{args.backend}"
        series = {"host RSS [MB]": ([s[0] + 1 for s in samples], [s[2] for s in samples])}
        if torch.cuda.is_available():
            series["GPU memory in use [MB]"] = ([s[0] + 1 for s in samples],
                                                [s[3] for s in samples])
        common.save_plot(args, name, series, "batch", "MB", f"soak: {args.backend}")
        common.save(args, name, f"Soak, {args.backend} backend", [table])
    if rss_growth >= GROWTH_LIMIT_MB or not gpu_ok or stats["compiles"] > 1:
        sys.exit(1)


if __name__ == "__main__":
    main()
