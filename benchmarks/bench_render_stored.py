"""Pixels from stored states: a store of states rendering its camera on read, next to the
engine streaming the same camera (simulating and rendering), in frames per second (one image of
one trajectory), alternately in one process; and the store's size against a store of the same
frames kept as images.

Streaming: `SimDataset(record=("state", Camera))`, timed batches after a warm-up. Reading:
`StoredDataset(path, cameras=Camera, backend=)` of a store written with `record=("state",)`:
- the CPU renderer: a `DataLoader` of trajectories (`--read-batch` per batch) with
  `--read-workers` workers (target: at least 0.8x streaming on the 2-core machine, 2 workers);
- MuJoCo Warp's renderer: `transitions().loader(--transition-batch)` on the GPU, both frames of
  every transition rendered (target: at least 0.8x streaming on an H200).

    python benchmarks/bench_render_stored.py --quick
    python benchmarks/bench_render_stored.py --save --tag cpu                       # 2 cores
    python benchmarks/bench_render_stored.py --backend warp --workloads humanoid:1024x100 \\
        --camera back --save --tag warp --results-dir $OUT                           # a GPU
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time

import torch

import common
import simloader
from simloader import bench

DEFAULT = [common.Workload("cartpole", 32, 50)]
QUICK = [common.Workload("cartpole", 8, 10)]
TARGET = 0.8


def dataset(w: common.Workload, args, camera=None) -> simloader.SimDataset:
    record = ("state",) + ((camera,) if camera is not None else ())
    options = {"nthread": common.cpu_count()} if args.backend == "cpu" else {}
    return simloader.SimDataset(w.name, backend=args.backend, nbatch=w.nbatch, nstep=w.nstep,
                                control=simloader.controls.Uniform(), seed=args.seed,
                                record=record, **options)


def stream(ds: simloader.SimDataset, frames: int) -> float:
    """Seconds per frame of streaming until `frames` frames were delivered (warm-up
    excluded)."""
    it = iter(ds)
    next(it)
    common.sync()
    per = ds.config.nbatch * ds.config.nstep
    start, done = time.perf_counter(), 0
    while done < frames:
        next(it)
        common.sync()
        done += per
    seconds = time.perf_counter() - start
    it.close()
    return seconds / done


def size(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK)
    p.add_argument("--backend", default="cpu", choices=("cpu", "warp"))
    p.add_argument("--camera", default="front", help="the model's camera (name)")
    p.add_argument("--size", type=int, default=64, help="image height and width")
    p.add_argument("--frames", type=int, help="frames per measure (default 20000, --quick 400)")
    p.add_argument("--batches", type=int, default=3, help="batches in the stores")
    p.add_argument("--read-workers", type=int, default=2)
    p.add_argument("--read-batch", type=int, default=8, help="trajectories per read batch")
    p.add_argument("--transition-batch", type=int, default=4096)
    p.add_argument("--folder", help="where the stores go (default: a temporary folder)")
    args = p.parse_args()
    frames = args.frames or (400 if args.quick else 20000)
    camera = simloader.Camera(args.camera, height=args.size, width=args.size)
    key = f"camera/{args.camera}/rgb"
    folder = tempfile.mkdtemp(prefix="bench_render_stored-", dir=args.folder)
    rows = []
    try:
        for w in common.workloads(args, DEFAULT, QUICK):
            states = simloader.write(dataset(w, args), os.path.join(folder, "s.zarr"),
                                     batches=args.batches, progress=False)
            images = simloader.write(dataset(w, args, camera), os.path.join(folder, "i.zarr"),
                                     batches=args.batches, progress=False)
            streaming = dataset(w, args, camera)
            if args.backend == "cpu":
                stored = simloader.StoredDataset(states, cameras=camera, keys=["state"])
                loader = torch.utils.data.DataLoader(
                    stored, batch_size=args.read_batch, shuffle=True,
                    num_workers=args.read_workers, persistent_workers=args.read_workers > 0,
                    multiprocessing_context="spawn" if args.read_workers else None)
                how = (f"DataLoader of trajectories, {args.read_batch} per batch, "
                       f"{args.read_workers} workers (spawn)")
                measure = {"read": lambda: bench.read_frames(loader, frames, w.nstep, key)}
            else:
                stored = simloader.StoredDataset(states, cameras=camera, backend=args.backend,
                                                 device="cuda", keys=["state"])
                transitions = stored.transitions()
                loader = transitions.loader(min(args.transition_batch, len(transitions)),
                                            order="random")
                how = (f"transitions().loader({args.transition_batch}) on the GPU, both "
                       f"frames of each transition")
                measure = {"read": lambda: bench.read_frames(loader, frames, 2, key)}
            results = common.interleave({"stream": lambda: stream(streaming, frames),
                                         **measure}, args.repeats, desc=str(w))
            streamed, rendered = 1 / results["stream"], 1 / results["read"]
            ratio = rendered / streamed
            rows.append([str(w), f"{streamed:,.0f}", f"{rendered:,.0f}",
                         f"{ratio:.2f}x ({'met' if ratio >= TARGET else 'missed'})",
                         f"{size(states) / 2**20:.1f} MiB", f"{size(images) / 2**20:.1f} MiB",
                         f"{size(images) / size(states):.1f}x", how])
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    table = common.markdown_table(
        ["workload", "streaming the camera, frames/s", "rendered on read, frames/s",
         f"read / stream (target >= {TARGET}x)", "store of states", "store of images",
         "images / states", "how it was read"], rows)
    notes = (f"backend={args.backend!r}, camera {args.camera!r} {args.size}x{args.size} RGB; "
             f"{frames} frames per measure, medians of {args.repeats} alternating repetitions; "
             f"stores of {args.batches} batches (images compressed with zstd, states raw).")
    common.report(args, "bench_render_stored", "Pixels rendered from stored states",
                  [notes, table])


if __name__ == "__main__":
    main()
