"""Soak: stream many batches and watch host RSS and GPU memory stay flat, with no recompilation.

Streams `--batches` batches (10^5 by default) of `--nbatch` x `--nstep` (16 x 10: tiny, so that
simloader's own per-batch work, where a leak would hide, dominates the simulation) from one
dataset, with random controls and initial states, sampling the process's resident memory and
the GPU memory in use (by every process, from the driver) every `--every` batches. It reports the
growth from the end of the warm-up (the first 10% of batches) to the end, the largest growth in
between and the fitted trend, against a limit of 50 MB. With MJX, a first iterator delivers one
batch (and compiles); the soak's iterator then must not trace, compile or load any JAX
computation: every JAX trace and compilation in the process after that first batch is counted.
Prints a table and, with --save, writes it with a plot of memory over the batches.

`--time-limit` ends a soak early (reported as incomplete, exit status 2) so that its results
still come back from a machine with a time limit. Exit status 1: a check failed.

    python benchmarks/soak.py --backend cpu --quick
    python benchmarks/soak.py --backend mjx --save --results-dir $OUT      # on the GPU machine
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Optional

import numpy as np
import torch

import common
import simloader

GROWTH_LIMIT_MB = 50.0
WARM_UP = 0.1  # fraction of the batches before the reference sample
SAMPLE_S = 5.0  # a memory sample at least this often (seconds)
# JAX's monitoring events of a trace and of an XLA compilation
JAX_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                      "/jax/core/compile/backend_compile_duration")


def host_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def gpu_used_mb() -> float:
    """Memory in use on GPU 0 by every allocator (JAX's and torch's), from the driver."""
    if not torch.cuda.is_available():
        return float("nan")
    free, total = torch.cuda.mem_get_info()
    return (total - free) / 2**20


class JaxCompilations:
    """Counts JAX traces and XLA compilations in this process from now on (JAX's monitoring
    events: they cover every jitted function, not only simloader's batch function)."""

    def __init__(self) -> None:
        import jax
        self.count = 0
        self._monitoring = jax.monitoring
        self._monitoring.register_event_duration_secs_listener(self._seen)

    def _seen(self, event: str, duration: float, **kwargs) -> None:
        if event in JAX_COMPILE_EVENTS:
            self.count += 1

    def close(self) -> None:
        self._monitoring.unregister_event_duration_listener(self._seen)


def growth(samples: list[tuple], column: int, start: int) -> tuple[float, float, float]:
    """(end - reference, largest - reference, fitted MB per 10^4 batches) of a column of the
    samples from sample `start` (the reference) on; NaNs where the column is NaN (no GPU)."""
    batch = np.array([s[0] for s in samples[start:]], dtype=float)
    values = np.array([s[column] for s in samples[start:]], dtype=float)
    if np.isnan(values).any():
        return (float("nan"),) * 3
    slope = np.polyfit(batch, values, 1)[0] * 1e4 if len(values) > 2 else float("nan")
    return values[-1] - values[0], values.max() - values[0], slope


def verdict(value: float) -> str:
    return "n/a" if value != value else ("ok" if value < GROWTH_LIMIT_MB else "FAIL")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--backend", default="cpu", choices=("cpu", "mjx"))
    parser.add_argument("--model", default="cartpole",
                        help="a model simloader loads: a built-in name or an MJCF path")
    parser.add_argument("--batches", type=int, default=100_000)
    parser.add_argument("--nbatch", type=int, default=16, help="trajectories per batch")
    parser.add_argument("--nstep", type=int, default=10, help="steps per trajectory")
    parser.add_argument("--every", type=int, default=0,
                        help="memory sample period in batches (default: 1%% of --batches); "
                             f"also every {SAMPLE_S:.0f} s")
    parser.add_argument("--time-limit", type=float,
                        help="seconds after which the soak stops early (reported incomplete)")
    parser.add_argument("--quick", action="store_true", help="2,000 batches")
    parser.add_argument("--save", action="store_true",
                        help="write the table and the plot to RESULTS_DIR/soak-<backend>-<date>.*")
    parser.add_argument("--results-dir", default=common.REPO / "benchmarks" / "results",
                        type=common.pathlib.Path, help="where --save writes (GPU machine: $OUT)")
    parser.add_argument("--tag", default="", help="suffix of the saved file names")
    args = parser.parse_args()
    if args.quick:
        args.batches = 2000
    if args.batches < 10:
        parser.error(f"--batches must be at least 10 (a warm-up and a soak), got {args.batches}")
    every = args.every or max(1, args.batches // 100)

    ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                              nstep=args.nstep, control=simloader.controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(), seed=0,
                              device="cuda" if torch.cuda.is_available() else None)
    # the first batch of the configuration, in an iterator of its own: it compiles (MJX)
    first = iter(ds)
    next(first)
    first.close()
    compilations: Optional[JaxCompilations] = (JaxCompilations() if args.backend == "mjx"
                                               else None)
    samples = []  # (batches delivered, seconds, host RSS MB, GPU MB)
    checksum, delivered, stopped = 0.0, 0, False
    start = time.perf_counter()
    stream = iter(ds)
    try:
        for batch in common.progress(stream, desc=f"soak {args.backend}", total=args.batches):
            delivered += 1
            now = time.perf_counter() - start
            stopped = args.time_limit is not None and now > args.time_limit
            # every `every` batches, and every few seconds (a soak cut short still has a series)
            if (delivered % every == 0 or delivered in (1, args.batches) or stopped
                    or now - samples[-1][1] >= SAMPLE_S):
                common.sync()
                checksum += float(batch["state"][0, -1, 1])  # touch the data
                samples.append((delivered, now, host_rss_mb(), gpu_used_mb()))
            if delivered == args.batches or stopped:
                break
    finally:
        stream.close()
        if compilations is not None:
            compilations.close()
    wall = time.perf_counter() - start

    reference = next(i for i, s in enumerate(samples) if s[0] >= WARM_UP * delivered)
    warm = samples[reference]
    rss_end, rss_peak, rss_trend = growth(samples, 2, reference)
    gpu_end, gpu_peak, gpu_trend = growth(samples, 3, reference)
    recompiled = compilations.count if compilations is not None else None
    failed = (verdict(rss_end) == "FAIL" or verdict(rss_peak) == "FAIL"
              or verdict(gpu_end) == "FAIL" or verdict(gpu_peak) == "FAIL" or bool(recompiled))
    stats = ds.stats
    rows = [
        ["batches", f"{delivered:,} of {args.batches:,}"
                    + (" (stopped by --time-limit: incomplete)" if stopped else "")],
        ["wall time, rate", f"{wall:.0f} s, {delivered / wall:,.0f} batches/s "
                            f"({1e3 * wall / delivered:.2f} ms per batch)"],
        ["reference sample (end of warm-up)", f"after {warm[0]:,} batches"],
        ["host RSS at the reference / at the end", f"{warm[2]:.0f} MB / {samples[-1][2]:.0f} MB"],
        ["host RSS growth after warm-up: at the end, largest",
         f"{rss_end:+.1f} MB ({verdict(rss_end)}), {rss_peak:+.1f} MB ({verdict(rss_peak)})"],
        ["host RSS trend after warm-up", f"{rss_trend:+.2f} MB per 10,000 batches"],
    ] + ([
        ["GPU memory at the reference / at the end", f"{warm[3]:.0f} MB / {samples[-1][3]:.0f} MB"],
        ["GPU memory growth after warm-up: at the end, largest",
         f"{gpu_end:+.1f} MB ({verdict(gpu_end)}), {gpu_peak:+.1f} MB ({verdict(gpu_peak)})"],
        ["GPU memory trend after warm-up", f"{gpu_trend:+.2f} MB per 10,000 batches"],
    ] if torch.cuda.is_available() else [["GPU memory", "n/a (no GPU)"]]) + [
        ["JAX traces + compilations after the first batch (must be 0)",
         "n/a (no JAX)" if recompiled is None else
         f"{recompiled} ({'ok' if not recompiled else 'FAIL'})"],
        ["simloader compilations, compile time",
         f"{stats.get('compiles', 0)}, {stats.get('compile_s', 0.0):.1f} s"],
        ["diverged trajectories", f"{stats['diverged']:,}"],
        ["verdict", "FAIL" if failed else ("incomplete" if stopped else "ok")],
    ]
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU"
    table = common.markdown_table(
        ["soak", f"{args.backend}, {args.model} {args.nbatch} x {args.nstep}, {device}"], rows)
    notes = (f"Memory sampled every {every:,} batches and every {SAMPLE_S:.0f} s; growth limit {GROWTH_LIMIT_MB:.0f} MB "
             f"after the first {WARM_UP:.0%} of the batches. GPU memory: in use on GPU 0 by "
             f"every process, from the driver.")
    # the series, thinned to about 11 rows (every 10%), for the record in text
    stride = max(1, (len(samples) - 1) // 10)
    series_table = common.markdown_table(
        ["batches delivered", "seconds", "host RSS MB", "GPU memory MB"],
        [[f"{b:,}", f"{t:.0f}", f"{rss:.1f}", "-" if gpu != gpu else f"{gpu:.0f}"]
         for b, t, rss, gpu in samples[::stride] + ([samples[-1]] if (len(samples) - 1) % stride
                                                    else [])])
    print(table + "\n\n" + notes + "\n\n" + series_table)
    if args.save:
        name = f"soak-{args.backend}"
        # growth from the reference sample, next to the limit (absolute values: the table)
        x = [s[0] for s in samples]
        series = {"host RSS [MB]": (x, [s[2] - warm[2] for s in samples])}
        if torch.cuda.is_available():
            series["GPU memory in use [MB]"] = (x, [s[3] - warm[3] for s in samples])
        series[f"limit (+{GROWTH_LIMIT_MB:.0f} MB)"] = ([x[0], x[-1]], [GROWTH_LIMIT_MB] * 2)
        figure = common.save_plot(args, name, series, "batches delivered",
                                  f"MB more than after {warm[0]:,} batches",
                                  f"soak: {args.backend}, {args.nbatch} x {args.nstep}",
                                  log=False)
        sections = [notes, table, series_table] + (
            [f"![memory over the soak]({figure.name})"] if figure else [])
        common.save(args, name, f"Soak, {args.backend} backend", sections)
    sys.exit(1 if failed else 2 if stopped else 0)


if __name__ == "__main__":
    main()
