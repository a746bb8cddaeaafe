"""A store read while it is written and grown: readers never see a healthy store as damaged.

One process grows a store from `--start` to `--slots` batch slots in `--steps` successive
`simloader.write` calls (each one a growth: the slots' array, then the root, then the new
slots), while `--readers` other processes open it again and again with `StoredDataset` (and
read its newest trajectory) until the writer is done. Each reader counts its opens, its
refusals (`DamagedStore`, which must be 0) and whether the number of trajectories it saw
ever went down (it must not: an open sees the committed slots of one moment, later than the
last). Exit status 1 on any refusal.

    python benchmarks/experiments/store_read_while_growing.py      # 200 -> 1200 slots, 2 readers
    python benchmarks/experiments/store_read_while_growing.py --save  # also benchmarks/results/
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import platform
import sys
import tempfile
import time

import simloader
from simloader.store import DamagedStore


def dataset() -> simloader.SimDataset:
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=20, nthread=1,
                                seed=1, record=("state", "sensordata", "qpos"),
                                control=simloader.controls.Uniform())


def grow(path: str, sizes: list[int], done) -> None:
    try:
        for batches in sizes:
            simloader.write(dataset(), path, batches=batches, progress=False)
    finally:
        done.set()


def read(path: str, done, out) -> None:
    opens, refusals, shrank, seen, first = 0, [], 0, 0, None
    while not done.is_set():
        try:
            stored = simloader.StoredDataset(path)
            if len(stored) < seen:
                shrank += 1
            seen = len(stored)
            if seen:
                stored[seen - 1]
        except DamagedStore as e:
            refusals.append(str(e)[:300])
        first = seen if first is None else first
        opens += 1
    out.put({"opens": opens, "refusals": refusals, "shrank": shrank, "first": first,
             "last": seen})


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--start", type=int, default=200, help="slots written before the readers")
    p.add_argument("--slots", type=int, default=1200, help="slots at the end")
    p.add_argument("--steps", type=int, default=5, help="growths from --start to --slots")
    p.add_argument("--readers", type=int, default=2)
    p.add_argument("--save", action="store_true")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "growing.zarr")
        t0 = time.perf_counter()
        simloader.write(dataset(), path, batches=args.start, progress=False)
        step = (args.slots - args.start) / args.steps
        sizes = [round(args.start + step * (k + 1)) for k in range(args.steps)]
        ctx = mp.get_context("spawn")
        done, out = ctx.Event(), ctx.Queue()
        readers = [ctx.Process(target=read, args=(path, done, out))
                   for _ in range(args.readers)]
        for r in readers:
            r.start()
        t1 = time.perf_counter()
        writer = ctx.Process(target=grow, args=(path, sizes, done))
        writer.start()
        writer.join()
        grown = time.perf_counter() - t1
        results = [out.get(timeout=600) for _ in readers]
        for r in readers:
            r.join()
        final = len(simloader.StoredDataset(path, verify=True)) // dataset().config.nbatch
    opens = sum(r["opens"] for r in results)
    refusals = sum(len(r["refusals"]) for r in results)
    lines = [
        f"# A store read while it grows ({time.strftime('%Y-%m-%d')})",
        "",
        f"- machine: {os.cpu_count()} CPU cores, "
        f"Python {platform.python_version()}, simloader {simloader.__version__}",
        "- command: `python benchmarks/experiments/store_read_while_growing.py "
        f"--start {args.start} --slots {args.slots} --steps {args.steps} --readers {args.readers}`",
        f"- store: cartpole, 4 trajectories x 20 steps a slot; {args.start} slots first "
        f"({t1 - t0:.1f} s), then grown to {sizes} in {grown:.1f} s by one process; "
        f"{final} slots at the end, verified (every checksum)",
        "",
        "| reader | opens | refusals | trajectories seen first -> last | times fewer than "
        "the open before |",
        "| --- | --- | --- | --- | --- |",
    ]
    for k, r in enumerate(results):
        lines.append(f"| {k} | {r['opens']} | {len(r['refusals'])} | {r['first']} -> "
                     f"{r['last']} | {r['shrank']} |")
    lines += ["", f"**{opens} opens, {refusals} refusals.**"]
    for r in results:
        for message in r["refusals"][:3]:
            lines.append(f"- refused: {message}")
    text = "\n".join(lines)
    print(text)
    if args.save:
        name = f"store_read_while_growing-{time.strftime('%Y-%m-%d')}.md"
        folder = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # benchmarks/
        with open(os.path.join(folder, "results", name), "w") as f:
            f.write(text + "\n")
    return 1 if refusals or any(r["shrank"] for r in results) or final != args.slots else 0


if __name__ == "__main__":
    sys.exit(main())
