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


def peaks(samples: list[tuple[float, float]], warm_minutes: float,
          window: float) -> tuple[float, float]:
    """The highest GPU memory sampled in the first `window` minutes after warm-up and in the
    last `window` minutes: a training loop's memory swings with its batch shapes (torch's
    caching allocator, `empty_cache`), so two single samples compare two points of the swing,
    where the peaks of two windows compare what the loop holds at most, early and late."""
    end = samples[-1][0]
    early = [g for m, g in samples if warm_minutes <= m <= warm_minutes + window]
    late = [g for m, g in samples if m >= end - window]
    return max(early), max(late)


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
    window = max(args.minutes / 10, 0.05)
    early, late = peaks(samples, min(1.0, args.minutes / 4), window)
    rows = [["minutes", f"{(time.perf_counter() - start) / 60:.1f}"],
            ["training steps (batches of the train stream)", step],
            ["train / validation batches", f"{train.stats['batches']} / "
                                            f"{valid.stats['batches']}"],
            ["steps simulated", f"{train.stats['steps'] + valid.stats['steps']:,}"],
            ["graph captures (train, validation)", f"{train.stats['graph_captures']}, "
                                                   f"{valid.stats['graph_captures']}"],
            ["GPU memory used after warm-up (one sample)", f"{used_warm:.2f} GiB"],
            ["GPU memory used at the end (one sample)", f"{used_end:.2f} GiB"],
            [f"peak in the first {window:.1f} minutes after warm-up", f"{early:.3f} GiB"],
            [f"peak in the last {window:.1f} minutes", f"{late:.3f} GiB"],
            ["growth of the peak", f"{100 * (late - early) / early:+.2f}%"]]
    sections = [markdown_table(["what", "measured"], rows)]
    common.report(args, "soak_warp", "Soak: a training loop with a Warp train and validation "
                                     "stream", sections)
    if args.save:  # every sample, for a later look
        common.result_path(args, "soak_warp", ".csv").write_text(
            "minutes,gib\n" + "".join(f"{m:.4f},{g:.4f}\n" for m, g in samples))
    if args.save and samples:
        common.save_plot(args, "soak_warp", {"GPU memory used": (
            [m for m, _ in samples], [g for _, g in samples])}, "minutes", "GiB",
            "GPU memory during the soak", log=False)


if __name__ == "__main__":
    main()
