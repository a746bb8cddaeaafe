"""Windows against transitions on one store: frames per second through each loader.

A store of humanoid states is written once (CPU engine); then, alternately in one process,
`stored.windows(LENGTH).loader(B_w, num_workers=W)` and `stored.transitions().loader(B_t,
num_workers=W)` are read for `--seconds` each after a warm-up batch, `--repeats` times. A
window delivers `B_w x LENGTH` frames a batch, a transition one new frame (`next/state`; its
`state` is the frame before), so frames/s compare what a world model consumes. The target
(issue 63): windows at least 0.8x the transitions' frames/s on the 2-core machine.

    python benchmarks/bench_windows.py --quick
    python benchmarks/bench_windows.py --save           # the 2-core figure
    python benchmarks/bench_windows.py --camera 64 --render warp --workers 0 --save --tag h200

With `--camera N`, windows and transitions carry an N x N camera rendered on read by
`--render` ("warp": MuJoCo Warp's renderer on the GPU, every frame of a batch one world), and
a third line streams the same camera live (`SimDataset(backend=--render, record=(state,
camera))`, `--stream-nbatch` trajectories of 200 steps) for the frames/s a live stream gives
(target: windows at batch 16 and 256 at least 0.8x of it, and 1M frames/s at 256).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

import torch

import common  # noqa: F401  (puts the checkout on the path)
import simloader


def frames_per_second(loader, frames_per_item: int, seconds: float) -> float:
    it = iter(loader)
    next(it)  # warm: workers started, shards mapped
    n, start = 0, time.perf_counter()
    for batch in it:
        n += len(batch["state"]) * frames_per_item
        if time.perf_counter() - start >= seconds:
            break
    common.sync()  # the frames rendered on the GPU, all of them, are in the time
    elapsed = time.perf_counter() - start
    del it
    return n / elapsed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--length", type=int, default=64, help="frames per window")
    p.add_argument("--window-batch", type=int, default=256)
    p.add_argument("--transition-batch", type=int, default=4096)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--batches", type=int, default=16, help="store batches of 256 x 200")
    p.add_argument("--camera", type=int, help="render an N x N camera on read")
    p.add_argument("--render", default="cpu", choices=("cpu", "warp"),
                   help="the engine that renders on read (warp: on the GPU)")
    p.add_argument("--window-batches", type=int, nargs="+", default=None,
                   help="window batch sizes (default: --window-batch)")
    p.add_argument("--stream-nbatch", type=int, default=1024)
    p.add_argument("--camera-name", default="back", help="the humanoid's camera")
    common.add_output_options(p)
    args = p.parse_args()
    nbatch, nstep = 256, 200
    if args.quick:
        args.batches, args.seconds, args.repeats, nbatch, nstep = 2, 1.0, 1, 64, 100
    folder = tempfile.mkdtemp()
    path = os.path.join(folder, "humanoid.zarr")
    ds = simloader.SimDataset("humanoid", backend="cpu", nbatch=nbatch, nstep=nstep, seed=0,
                              control=simloader.controls.Uniform(), record=("state",))
    simloader.write(ds, path, batches=args.batches, progress=False)
    camera = None if args.camera is None else \
        simloader.Camera(args.camera_name, height=args.camera, width=args.camera)
    options = {} if camera is None else dict(
        cameras=camera, backend=args.render, device="cuda" if args.render == "warp" else None)
    stored = simloader.StoredDataset(path, **options)
    windows, transitions = stored.windows(args.length), stored.transitions()
    sizes = args.window_batches or [args.window_batch]
    rates = {**{f"windows {b}": [] for b in sizes}, "transitions": [], "stream": []}
    stream = None
    if camera is not None:
        stream = simloader.SimDataset("humanoid", backend=args.render, nbatch=args.stream_nbatch,
                                      nstep=200, seed=1, control=simloader.controls.Uniform(),
                                      record=("state", camera))
    for _ in range(args.repeats):
        for b in sizes:
            rates[f"windows {b}"].append(frames_per_second(
                windows.loader(b, num_workers=args.workers, seed=0), args.length,
                args.seconds))
        rates["transitions"].append(frames_per_second(
            transitions.loader(args.transition_batch, num_workers=args.workers, seed=0), 1,
            args.seconds))
        if stream is not None:
            rates["stream"].append(frames_per_second(
                torch.utils.data.DataLoader(stream, batch_size=None), 200, args.seconds))
    t = statistics.median(rates["transitions"])
    s = statistics.median(rates["stream"]) if stream is not None else None
    rows = []
    for b in sizes:
        w = statistics.median(rates[f"windows {b}"])
        against = f"; {w / s:.3f}x the live stream" if s else ""
        rows.append(f"| `windows({args.length}).loader` | {b} windows | {w / 1e6:.3f}M | "
                    f"{w / t:.3f}x (target >= 0.8x){against} |")
    rows.append(f"| `transitions().loader` | {args.transition_batch} transitions | "
                f"{t / 1e6:.3f}M | 1x |")
    if s:
        rows.append(f"| live stream, `backend={args.render!r}` | {args.stream_nbatch} x 200 "
                    f"frames | {s / 1e6:.3f}M | {s / t:.3f}x |")
    seen = "" if camera is None else (f", a {args.camera} x {args.camera} camera rendered on "
                                      f"read by {args.render!r}")
    table = "\n".join([
        f"humanoid store: {args.batches} x {nbatch} trajectories of {nstep} steps (states "
        f"only, {len(stored)} trajectories){seen}; {args.workers} DataLoader workers; medians "
        f"of {args.repeats} alternating repeats of {args.seconds} s each",
        "",
        "| loader | batch | frames/s | ratio to transitions |",
        "| --- | --- | --- | --- |", *rows])
    common.report(args, "bench_windows", "Windows against transitions, frames per second",
                  [table])


if __name__ == "__main__":
    main()
