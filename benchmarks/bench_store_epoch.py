"""An epoch over a store bigger than memory, next to the disk's sequential read speed.

A store of at least `--gb` GB (default 30; more than this machine's memory) is written with
`simloader.write` (CPU backend, all cores; the write's cost next to generation is
`bench_write.py`'s), flushed, and dropped from the page cache (`posix_fadvise(DONTNEED)` on
every file: what another process's reads would have done). Then, each from a cold cache:

1. the disk's sequential read speed: `--sample-gb` of the store's shard files read whole, in
   order, 16 MiB at a time (what `cat` does);
2. one epoch of `StoredDataset.transitions().loader(4096, order="quasi_random")` with
   `--workers` DataLoader workers: every transition once; the speed is the bytes of the
   arrays it reads (state, control, initial_state) over the epoch's time;
3. the same loader in `order="random"` for `--random-seconds` (a full random epoch over a store
   the page cache cannot hold reads a page per transition).

The ratio of 2 to 1 is the target (at least 0.8x, performance.md); the randomness of each
order is the mean distance between consecutive indices in a batch (`order.mean_jump`; n/3 for
a uniform permutation). The store is deleted at the end unless `--keep`.

    python benchmarks/bench_store_epoch.py --gb 30 --save     # the 2-core figure (~40 min)
    python benchmarks/bench_store_epoch.py --gb 1 --quick     # a smoke run
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import tempfile
import time


import common
import simloader
from simloader.store import order as orders

READ_KEYS = ("state", "control", "initial_state")  # what the transitions view reads


def files_of(path: str, keys=None) -> list[str]:
    """The store's shard files (of `keys`' arrays), in order of name."""
    out = []
    for directory, _, files in os.walk(path):
        rel = os.path.relpath(directory, path)
        if "/c" not in "/" + rel.replace(os.sep, "/") + "/":
            continue
        if keys is not None and rel.split(os.sep)[0] not in keys:
            continue
        out += [os.path.join(directory, f) for f in files]
    return sorted(out)


def evict(files: list[str]) -> None:
    """Drops the files from the page cache (their pages are clean after `os.sync`)."""
    os.sync()
    for file in files:
        fd = os.open(file, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(fd)


def sequential_read(files: list[str], limit: int) -> tuple[float, int]:
    """Bytes/s of reading `files` whole and in order, up to `limit` bytes."""
    buffer = bytearray(16 << 20)
    done, start = 0, time.perf_counter()
    for file in files:
        with open(file, "rb", buffering=0) as f:
            while n := f.readinto(buffer):
                done += n
        if done >= limit:
            break
    return done / (time.perf_counter() - start), done


def epoch(transitions, order: str, batch: int, workers: int, seconds: float,
          seed: int) -> tuple[float, int, float]:
    """(seconds, transitions read, mean jump) of one epoch in `order`, or of `seconds` of it."""
    loader = transitions.loader(batch, order=order, num_workers=workers, seed=seed,
                                persistent_workers=False)
    jump = orders.mean_jump(loader.sampler)
    count, start = 0, time.perf_counter()
    for item in common.progress(loader, f"{order} epoch", total=len(loader)):
        count += len(item["control"])
        if time.perf_counter() - start > seconds:
            break
    return time.perf_counter() - start, count, jump


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--gb", type=float, default=30.0, help="the store's size (GB, 1e9 bytes)")
    p.add_argument("--model", default="humanoid")
    p.add_argument("--nbatch", type=int, default=256)
    p.add_argument("--nstep", type=int, default=100)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch", type=int, default=4096, help="transitions per batch")
    p.add_argument("--sample-gb", type=float, default=8.0,
                   help="GB read sequentially for the disk's speed")
    p.add_argument("--random-seconds", type=float, default=120.0)
    p.add_argument("--folder", help="where the store goes (default: a temporary folder)")
    p.add_argument("--keep", action="store_true", help="keep the store")
    p.add_argument("--store", help="a store an earlier --keep run left (same sizes): resumed "
                                   "as simloader.write resumes (nothing to write if whole) "
                                   "and kept")
    common.add_output_options(p)
    args = p.parse_args()

    model = simloader.load_model(args.model)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=args.nbatch, nstep=args.nstep,
                              control=simloader.controls.Uniform(), record=("state",),
                              nthread=common.cpu_count())
    nstate = mujoco_state_size(model)
    per_slot = args.nbatch * (args.nstep + 1) * nstate * 8 + \
        args.nbatch * args.nstep * model.nu * 8
    batches = max(1, math.ceil(args.gb * 1e9 / per_slot))
    if args.store:
        folder, path, args.keep = None, args.store, True
    else:
        folder = tempfile.mkdtemp(prefix="bench_store_epoch-", dir=args.folder)
        path = os.path.join(folder, "store.zarr")
    try:
        start = time.perf_counter()
        simloader.write(ds, path, batches=batches, progress=True)
        os.sync()
        write_s = time.perf_counter() - start
        read_files = files_of(path, READ_KEYS)
        read_bytes = sum(os.path.getsize(f) for f in read_files)
        store_bytes = sum(os.path.getsize(f) for f in files_of(path))
        evict(files_of(path))
        seq_bw, seq_bytes = sequential_read(read_files, int(args.sample_gb * 1e9))
        evict(files_of(path))
        stored = simloader.StoredDataset(path)
        transitions = stored.transitions()
        quasi_s, quasi_n, quasi_jump = epoch(transitions, "quasi_random", args.batch,
                                             args.workers, math.inf, 0)
        assert quasi_n == len(transitions), (quasi_n, len(transitions))
        evict(files_of(path))
        random_s, random_n, random_jump = epoch(transitions, "random", args.batch,
                                                args.workers, args.random_seconds, 0)
        quasi_bw = read_bytes / quasi_s
        random_bw = read_bytes * random_n / len(transitions) / random_s
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        rows = [
            ["store", f"{store_bytes / 1e9:.1f} GB ({batches} slots of {args.nbatch} x "
                      f"{args.nstep} {args.model}); memory {memory / 1e9:.1f} GB",
             f"written in {write_s:.0f} s ({store_bytes / write_s / 1e6:.0f} MB/s)", ""],
            ["disk, sequential read (cold)", f"{seq_bw / 1e6:.0f} MB/s",
             f"{seq_bytes / 1e9:.1f} GB read whole in order", "1.00x"],
            [f"epoch, quasi_random, {args.workers} workers (cold)",
             f"{quasi_bw / 1e6:.0f} MB/s", f"{quasi_n / quasi_s / 1e6:.2f}M transitions/s; "
                                          f"{quasi_s:.0f} s; mean jump {quasi_jump:.3g}",
             f"**{quasi_bw / seq_bw:.2f}x**"],
            [f"random, {args.workers} workers (cold, {random_s:.0f} s)",
             f"{random_bw / 1e6:.3g} MB/s",
             f"{random_n / random_s:,.0f} transitions/s ({random_n} in {random_s:.0f} s); "
             f"mean jump {random_jump:.3g} (n = {len(transitions)})",
             f"{random_bw / seq_bw:.3f}x"],
        ]
        table = common.markdown_table(["what", "speed", "detail", "of sequential"], rows)
        common.report(args, "bench_store_epoch", "An epoch over a store bigger than memory",
                      [table, f"Epoch bytes: the arrays the transitions read "
                              f"({', '.join(READ_KEYS)}: {read_bytes / 1e9:.1f} GB)."])
        plot(args, {"sequential read": seq_bw, "quasi_random epoch": quasi_bw,
                    "random order": random_bw})
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)


def mujoco_state_size(model) -> int:
    import mujoco
    return mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)


def plot(args, speeds: dict[str, float]) -> None:
    if not args.save:
        return
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 3.5))
    names = list(speeds)
    ax.barh(names, [speeds[n] / 1e6 for n in names], color=["grey", "tab:blue", "tab:orange"])
    ax.set_xlabel("MB/s from a cold page cache")
    ax.set_title("Reading a store bigger than memory")
    fig.tight_layout()
    common.save_figure(args, "bench_store_epoch", fig)


if __name__ == "__main__":
    main()
