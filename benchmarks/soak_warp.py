"""Soak: a training loop fed by a Warp dataset, reading a Warp validation stream every few
steps, for minutes; GPU memory after warm-up against the end, graph captures, errors.

The loop does what trainers do: `loss.item()` and `torch.cuda.synchronize()` every step, a
model trained under `torch.autocast`, tensors of new shapes, `empty_cache()` now and then.
Run on the GPU machine:
  python benchmarks/soak_warp.py --minutes 20 --save --results-dir $OUT
"""

from __future__ import annotations

import time

import torch

import common
from common import markdown_table

import simloader
from simloader import controls


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], [], [], repeats=False)
    p.add_argument("--minutes", type=float, default=20.0)
    p.add_argument("--nbatch", type=int, default=4096)
    p.add_argument("--nstep", type=int, default=50)
    args = common.parse(p)
    if args.quick:
        args.minutes, args.nbatch, args.nstep = 0.2, 256, 10
    kwargs = dict(backend="mjx", impl="warp", control=controls.Uniform())
    train = simloader.SimDataset("humanoid", nbatch=args.nbatch, nstep=args.nstep, **kwargs)
    valid = simloader.SimDataset("humanoid", nbatch=args.nbatch // 4, nstep=args.nstep,
                                 seed=1, **kwargs)
    nstate = train.config.nstate
    model = torch.nn.Sequential(torch.nn.Linear(nstate, 256), torch.nn.ReLU(),
                                torch.nn.Linear(256, nstate)).cuda()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    it, vit = iter(train), iter(valid)
    start, warm, samples, step = time.perf_counter(), None, [], 0
    while time.perf_counter() - start < args.minutes * 60:
        batch = next(it)
        x = batch["state"][:, :-1].reshape(-1, nstate)[: 50000 + 13 * (step % 100)]
        y = batch["state"][:, 1:].reshape(-1, nstate)[: x.shape[0]]
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss = (model(x) - y).float().pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        loss.item()
        torch.cuda.synchronize()
        if step % 3 == 0:
            with torch.no_grad():
                model(next(vit)["state"].reshape(-1, nstate)).mean().item()
        if step % 50 == 0:
            torch.cuda.empty_cache()
        step += 1
        elapsed = time.perf_counter() - start
        if warm is None and elapsed > min(60.0, args.minutes * 15):
            warm = torch.cuda.mem_get_info()
        if step % 20 == 0:
            free, total = torch.cuda.mem_get_info()
            samples.append((elapsed / 60, (total - free) / 2**30))
    free, total = torch.cuda.mem_get_info()
    used_warm, used_end = (warm[1] - warm[0]) / 2**30, (total - free) / 2**30
    rows = [["minutes", f"{(time.perf_counter() - start) / 60:.1f}"],
            ["training steps (batches of the train stream)", step],
            ["train / validation batches", f"{train.stats['batches']} / "
                                            f"{valid.stats['batches']}"],
            ["steps simulated", f"{train.stats['steps'] + valid.stats['steps']:,}"],
            ["graph captures (train, validation)", f"{train.stats['graph_captures']}, "
                                                   f"{valid.stats['graph_captures']}"],
            ["GPU memory used after warm-up", f"{used_warm:.2f} GiB"],
            ["GPU memory used at the end", f"{used_end:.2f} GiB"],
            ["growth", f"{100 * (used_end - used_warm) / used_warm:+.2f}%"]]
    sections = [markdown_table(["what", "measured"], rows)]
    common.report(args, "soak_warp", "Soak: a training loop with a Warp train and validation "
                                     "stream", sections)
    if args.save and samples:
        common.save_plot(args, "soak_warp", {"GPU memory used": (
            [m for m, _ in samples], [g for _, g in samples])}, "minutes", "GiB",
            "GPU memory during the soak", log=False)


if __name__ == "__main__":
    main()
