"""Soak: a training loop fed by a Warp dataset, reading a Warp validation stream every few
steps, for minutes; GPU memory early against late (after `empty_cache()`), graph captures,
errors.

The loop does what trainers do: `loss.item()` and `torch.cuda.synchronize()` every step, a
model trained under `torch.autocast`, tensors of new shapes, `empty_cache()` now and then.
Run on the GPU machine:
  python benchmarks/soak_warp.py --minutes 20 --save --results-dir $OUT
"""

from __future__ import annotations

import pathlib
import statistics
import time

import torch

import common
from common import markdown_table

import simloader
from simloader import controls


def windows(samples: list[tuple[float, float]], warm_minutes: float,
            window: float) -> tuple[list[float], list[float]]:
    """The samples of the first `window` minutes after warm-up and of the last `window`."""
    end = samples[-1][0]
    early = [g for m, g in samples if warm_minutes <= m <= warm_minutes + window]
    late = [g for m, g in samples if m >= end - window]
    return early or [samples[0][1]], late


def memory_rows(held: list[tuple[float, float]], live: list[tuple[float, float]],
                minutes: float) -> list[list]:
    """GPU memory early against late. Samples are taken just after `empty_cache()`, where the
    loop holds only what is alive; what is alive still steps with the batches in flight (0 to
    the prefetch depth, per stream: one 4096 x 50 humanoid batch is ~45 MB), so single samples
    compare two points of that swing. The floor of a window (its fewest batches in flight)
    is what a leak would lift; the median is shown beside it."""
    warm, window = min(1.0, minutes / 4), max(minutes / 10, 0.05)
    rows = []
    for what, samples in (("GPU memory held (torch + Warp's pool)", held),
                          ("torch's live tensors", live)):
        early, late = windows(samples, warm, window)
        for stat, f in (("floor", min), ("median", statistics.median)):
            rows.append([f"{what}, {stat}: first {window:.1f} min after warm-up / last "
                         f"{window:.1f} min", f"{f(early):.3f} / {f(late):.3f} GiB "
                         f"({100 * (f(late) - f(early)) / f(early):+.2f}%)"])
    rows.append(["samples (after each 50th step's empty_cache)", len(held)])
    return rows


def from_csv(path: str) -> list[list]:
    """`memory_rows` of a saved run's samples."""
    lines = pathlib.Path(path).read_text().splitlines()[1:]
    values = [[float(v) for v in line.split(",")] for line in lines]
    held, live = [(m, g) for m, g, _ in values], [(m, a) for m, _, a in values]
    return memory_rows(held, live, held[-1][0])


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], [], [], repeats=False)
    p.add_argument("--minutes", type=float, default=20.0)
    p.add_argument("--nbatch", type=int, default=4096)
    p.add_argument("--nstep", type=int, default=50)
    p.add_argument("--from-csv", help="summarize the memory samples a saved run wrote "
                                      "(no GPU needed) instead of running")
    args = common.parse(p)
    if args.from_csv:
        print(markdown_table(["what", "measured"], from_csv(args.from_csv)))
        return
    if args.quick:
        args.minutes, args.nbatch, args.nstep = 0.2, 256, 10
    kwargs = dict(backend="warp", control=controls.Uniform())
    train = simloader.SimDataset("humanoid", nbatch=args.nbatch, nstep=args.nstep, **kwargs)
    valid = simloader.SimDataset("humanoid", nbatch=args.nbatch // 4, nstep=args.nstep,
                                 seed=1, **kwargs)
    nstate = train.config.nstate
    model = torch.nn.Sequential(torch.nn.Linear(nstate, 256), torch.nn.ReLU(),
                                torch.nn.Linear(256, nstate)).cuda()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    it, vit = iter(train), iter(valid)
    start, samples, allocated, step = time.perf_counter(), [], [], 0

    def elapsed_minutes() -> float:
        return (time.perf_counter() - start) / 60

    def held() -> float:
        """GiB this process holds on the GPU: torch's caching allocator and Warp's memory pool
        (MuJoCo Warp's arrays, what its graph captures allocate). Unlike the device's used
        memory, no other process on the GPU moves it."""
        import warp as wp
        return (torch.cuda.memory_reserved() + wp.get_mempool_used_mem_current("cuda:0")) / 2**30

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
            samples.append((elapsed_minutes(), held()))
            allocated.append((elapsed_minutes(), torch.cuda.memory_allocated() / 2**30))
        step += 1
    rows = [["minutes", f"{(time.perf_counter() - start) / 60:.1f}"],
            ["training steps (batches of the train stream)", step],
            ["train / validation batches", f"{train.stats['batches']} / "
                                            f"{valid.stats['batches']}"],
            ["steps simulated", f"{train.stats['steps'] + valid.stats['steps']:,}"],
            ["graph captures (train, validation)", f"{train.stats['graph_captures']}, "
                                                   f"{valid.stats['graph_captures']}"],
            *memory_rows(samples, allocated, args.minutes)]
    sections = [markdown_table(["what", "measured"], rows)]
    common.report(args, "soak_warp", "Soak: a training loop with a Warp train and validation "
                                     "stream", sections)
    if args.save:  # every sample, for a later look
        common.result_path(args, "soak_warp", ".csv").write_text(
            "minutes,held_gib,torch_allocated_gib\n" + "".join(
                f"{m:.4f},{g:.4f},{a:.4f}\n" for (m, g), (_, a) in zip(samples, allocated)))
    if args.save and samples:
        common.save_plot(args, "soak_warp", {
            "held (torch + Warp's pool)": ([m for m, _ in samples], [g for _, g in samples]),
            "torch's live tensors": ([m for m, _ in allocated], [a for _, a in allocated])},
            "minutes", "GiB", "GPU memory during the soak (after empty_cache)", log=False)


if __name__ == "__main__":
    main()
