"""What storing the stream costs, and how fast a store feeds training back.

Writing: `simloader.write` of `--batches` batches next to generating the same batches
without writing (a fresh iterator of the same dataset), alternately in one process, each
timed from start to the last batch in hand (first batch included in both); the write is
timed until `os.sync()` returns, so its batches are on the disk, not only in the page cache.
The cost is `1 - write throughput / generation throughput` (target: at most 0.15 on the
CPU engine, performance.md). Beside it: the disk's sequential speed (`dd bs=1M
conv=fdatasync` into the same folder, in the same run), the store's bytes per step, the disk's
bound in steps/s (speed / bytes per step), generate + write against the lower of the
generation rate and the disk's bound (target: at least 0.8x on a GPU), and the write
pipeline's report: seconds per batch in each stage and which one bounded the run.
`--compression zstd` writes states compressed; `--writers 1 2` also times writes by 1 and 2
DataLoader workers (each simulating with one thread) against each other.

Reading: `StoredDataset` of the last store written, through `DataLoader(shuffle=True,
num_workers=--read-workers)` as trajectories (`--read-batch` per batch) and as transitions
(`StoredDataset.transitions().loader(4096, order=)` in random and quasi-random order), for
`--read-seconds` each after a warm-up batch, in transitions per second (target: 1M with 2
workers on the 2-core machine). The store fits in the page cache here: an epoch over one
bigger than memory is `bench_store_epoch.py`'s.

    python benchmarks/bench_write.py --quick
    python benchmarks/bench_write.py --save                      # the 2-core figures
    python benchmarks/bench_write.py --backend warp --record state qvel \\
        --camera 64x64 --workloads humanoid:8192x200 --save --tag warp   # the GPU figure
    python benchmarks/bench_write.py --backend warp --workloads humanoid:8192x200 \\
        --read-seconds 0 --save --tag warp-pipeline        # the disk's bound (#50)
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import tempfile
import time
from typing import Optional

import torch

import common
import simloader
from simloader.store import pipeline

DEFAULT = [common.Workload("cartpole", 4096, 200), common.Workload("humanoid", 256, 100)]
QUICK = [common.Workload("cartpole", 256, 50), common.Workload("humanoid", 16, 20)]
TARGET_COST, TARGET_READ = 0.15, 1e6


def dataset(model, w: common.Workload, args, nthread=None) -> simloader.SimDataset:
    record = list(args.record)
    if args.camera:
        height, width = (int(v) for v in args.camera.lower().split("x"))
        # the model's first camera (MuJoCo Warp does not render the free camera, -1)
        camera = 0 if model.ncam else -1
        record.append(simloader.Camera(camera, height=height, width=width))
    options = {} if args.backend in ("mjx", "warp") else {
        "nthread": nthread or common.cpu_count()}  # all the cores, as the generation alone
    return simloader.SimDataset(model, backend=args.backend, nbatch=w.nbatch, nstep=w.nstep,
                                control=simloader.controls.Uniform(), seed=args.seed,
                                record=tuple(record), **options)


def generate(ds: simloader.SimDataset, nbatches: int) -> float:
    """Seconds per step of `nbatches` batches, generated and held, not kept."""
    start = time.perf_counter()
    it = iter(ds)
    for _ in range(nbatches):
        next(it)
        common.sync()
    seconds = time.perf_counter() - start
    it.close()
    return seconds / (nbatches * ds.config.nbatch * ds.config.nstep)


def write(ds: simloader.SimDataset, nbatches: int, folder: str, compression=None,
          num_workers: int = 0, reports: Optional[list] = None) -> float:
    """Seconds per step of writing `nbatches` batches into a fresh store, until on disk (the
    write's stage report appended to `reports`)."""
    path = os.path.join(folder, "store.zarr")
    shutil.rmtree(path, ignore_errors=True)
    os.sync()  # the previous store's deletion is not this one's cost
    start = time.perf_counter()
    written = simloader.write(ds, path, batches=nbatches, progress=False,
                              compression=compression, num_workers=num_workers)
    os.sync()
    if reports is not None:
        reports.append(written.report)
    return (time.perf_counter() - start) / (nbatches * ds.config.nbatch * ds.config.nstep)


def disk_speed(folder: str, mib: int) -> float:
    """Bytes per second of `dd if=/dev/zero bs=1M count=MIB conv=fdatasync` into `folder`
    (the disk's sequential write speed, data on the disk when it returns)."""
    target = os.path.join(folder, "dd.bin")
    os.sync()
    start = time.perf_counter()
    subprocess.run(["dd", "if=/dev/zero", f"of={target}", "bs=1M", f"count={mib}",
                    "conv=fdatasync"], check=True, capture_output=True)
    seconds = time.perf_counter() - start
    os.unlink(target)
    return mib * 2**20 / seconds


def stage_line(report) -> str:
    """Seconds per batch of each stage, and the bound."""
    per = max(report.batches, 1) * report.writers
    return "; ".join(f"{name} {report.stages.get(name, 0.0) / per:.3f}"
                     for name in pipeline.STAGES) + f"; bound: {report.bound}"


def read_rate(loader: torch.utils.data.DataLoader, per_item: int, seconds: float) -> float:
    """Transitions per second `loader` delivers (items of `per_item` transitions), after
    one warm-up batch; epochs follow each other until `seconds` passed."""
    items, start = 0, None
    while start is None or time.perf_counter() - start < seconds:
        seen = 0
        for batch in loader:
            seen += 1
            if start is None:
                start = time.perf_counter()  # after the workers started and the first batch
                continue
            items += len(batch["control"])
            if time.perf_counter() - start >= seconds:
                break
        if not seen:
            raise ValueError("the store holds less than one read batch: lower --read-batch")
    return items * per_item / (time.perf_counter() - start)


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK)
    p.add_argument("--batches", type=int,
                   help="batches per measure (default 12, --quick 3): a corpus is many "
                        "batches, and the disk flush the last ones wait for is amortized")
    p.add_argument("--backend", default="cpu", choices=("cpu", "mjx", "warp", "auto"))
    p.add_argument("--record", nargs="+", default=["state", "sensordata"])
    p.add_argument("--camera", help="HEIGHTxWIDTH: record the RGB of the model's first camera too "
                        "(the free camera if it has none)")
    p.add_argument("--read-workers", type=int, default=2)
    p.add_argument("--read-batch", type=int, default=32, help="trajectories per read batch")
    p.add_argument("--transition-batch", type=int, default=4096,
                   help="transitions per batch of the transitions view")
    p.add_argument("--read-seconds", type=float, default=5.0)
    p.add_argument("--folder", help="where the stores go (default: a temporary folder)")
    p.add_argument("--compression", choices=("zstd",), help="write(compression=)")
    p.add_argument("--writers", type=int, nargs="*", default=[],
                   help="also time writes by these numbers of DataLoader workers (each "
                        "simulating with one thread), e.g. 1 2")
    p.add_argument("--dd-mib", type=int, help="MiB that dd writes to measure the disk "
                                               "(default 4096, --quick 256)")
    args = p.parse_args()  # not common.parse: its --batches default (4) is a throughput one
    nbatches = args.batches or (3 if args.quick else 12)

    folder = tempfile.mkdtemp(prefix="bench_write-", dir=args.folder)
    rows, plot = [], {"generate": ([], []), "generate + write": ([], [])}
    pipelines, scaling = [], []
    try:
        disk = disk_speed(folder, args.dd_mib or (256 if args.quick else 4096))
        for w in common.workloads(args, DEFAULT, QUICK):
            # simloader's built-in models (or a path): what is measured is the writing
            model = (common.load_model(w.name, args.model_dir) if args.model_dir else
                     simloader.load_model(w.name))
            ds = dataset(model, w, args)
            generate(ds, 1)  # warm-up: threads, compilation, caches
            reports: list = []
            results = common.interleave(
                {"generate": lambda: generate(ds, nbatches),
                 "generate + write": lambda: write(ds, nbatches, folder, args.compression,
                                                   reports=reports)},
                args.repeats, desc=str(w))
            gen, wrote = (1 / results[k] for k in ("generate", "generate + write"))
            size = sum(os.path.getsize(os.path.join(d, f))
                       for d, _, fs in os.walk(os.path.join(folder, "store.zarr")) for f in fs)
            per_step = size / (nbatches * w.nbatch * w.nstep)
            bound = disk / per_step
            # the report of the median write
            report = sorted(reports, key=lambda r: r.seconds)[len(reports) // 2]
            pipelines.append([str(w), f"{per_step:.0f} B", f"{disk / 1e9:.2f} GB/s",
                              f"{bound / 1e6:.3f}M",
                              f"{wrote / min(gen, bound):.2f}x", stage_line(report)])
            for workers in args.writers:
                one = dataset(model, w, args, nthread=1)
                generate(one, 1)
                rate = 1 / statistics.median(
                    write(one, max(nbatches, 2 * workers), folder, args.compression, workers)
                    for _ in range(args.repeats))
                scaling.append([str(w), str(workers), f"{rate / 1e6:.3f}M"])
            stored = simloader.StoredDataset(os.path.join(folder, "store.zarr"))
            workers = {"num_workers": args.read_workers,
                       "persistent_workers": args.read_workers > 0}
            traj = trans = quasi = float("nan")
            if args.read_seconds > 0:
                traj = read_rate(torch.utils.data.DataLoader(
                    stored, batch_size=min(args.read_batch, len(stored)), shuffle=True,
                    **workers), w.nstep, args.read_seconds)
                transitions = stored.transitions()
                batch = min(args.transition_batch, len(transitions))
                trans, quasi = (read_rate(transitions.loader(batch, order=order, **workers), 1,
                                          args.read_seconds)
                                for order in ("random", "quasi_random"))
            cost = 1 - wrote / gen
            rows.append([str(w), f"{gen / 1e6:.3f}M", f"{wrote / 1e6:.3f}M",
                         f"{cost:.1%} ({'met' if cost <= TARGET_COST else 'missed'})",
                         f"{size / 2**20 / nbatches:.1f} MiB",
                         f"{traj / 1e6:.2f}M", f"{trans / 1e6:.2f}M; {quasi / 1e6:.2f}M"])
            for name, value in (("generate", gen), ("generate + write", wrote)):
                plot[name][0].append(str(w))
                plot[name][1].append(value)
            del stored
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    headers = ["workload", "generate steps/s", "generate + write steps/s",
               f"write cost (target <= {TARGET_COST:.0%})", "store per batch",
               f"read: trajectories, transitions/s ({args.read_workers} workers)",
               "read: transitions view, transitions/s (random; quasi_random order)"]
    table = common.markdown_table(headers, rows)
    pipeline_table = common.markdown_table(
        ["workload", "store bytes per step", "disk (dd bs=1M conv=fdatasync)",
         "disk's bound, steps/s", "generate + write / min(generate, disk's bound) "
         "(target >= 0.8x on a GPU)", "seconds per batch in each stage (median write)"],
        pipelines)
    sections = [table, "The write pipeline against the disk:", pipeline_table]
    if scaling:
        sections += ["Writers (DataLoader workers, one simulation thread each):",
                     common.markdown_table(["workload", "writers", "generate + write steps/s"],
                                           scaling)]
    recorded = " + ".join(args.record + ([f"camera {args.camera} RGB"] if args.camera else []))
    notes = (f"backend={args.backend!r}, compression={args.compression!r}"
             f", recording {recorded}; {nbatches} batches per measure, medians of "
             f"{args.repeats} alternating repetitions; writes timed until os.sync() returns. "
             f"Reads: DataLoader(shuffle=True, num_workers={args.read_workers}), "
             f"{args.read_batch} trajectories per batch, or transitions().loader"
             f"({args.transition_batch}, order='random' or 'quasi_random'), "
             f"{args.read_seconds:.0f} s each (target {TARGET_READ / 1e6:.0f}M transitions/s).")
    common.report(args, "bench_write", "Writing and reading simloader stores",
                  [notes, *sections])
    if args.save:
        _bars(args, plot)


def _bars(args, plot: dict) -> None:
    """Generation with and without writing, side by side per workload."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = plot["generate"][0]
    fig, ax = plt.subplots(figsize=(6, 4))
    for k, (label, (_, values)) in enumerate(plot.items()):
        ax.bar([i + 0.4 * k for i in range(len(names))], values, width=0.4, label=label)
    ax.set_xticks([i + 0.2 for i in range(len(names))], names)
    ax.set_ylabel("steps/s")
    ax.set_title("simloader.write: generation kept while writing")
    ax.legend()
    fig.tight_layout()
    common.save_figure(args, "bench_write", fig)


if __name__ == "__main__":
    main()
