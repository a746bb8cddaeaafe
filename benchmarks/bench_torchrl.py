"""simloader's torchrl collector against iterating the same SimDataset: steps per second.

One `SimDataset` (a policy in the loop) is read, alternately in one process, three ways for
`--seconds` each after a warm-up batch, `--repeats` times:

- `dataset`: `for batch in DataLoader(ds, batch_size=None)`, the batch's tensors touched;
- `collector`: `for td in SimCollector(ds)`: each batch as a TensorDict in torchrl's keys;
- `collector + buffer`: as `collector`, each batch's physics rows extended into a torchrl
  `ReplayBuffer(LazyTensorStorage(--capacity, device=the batch's))` with a `SliceSampler`
  over `("collector", "traj_ids")`, and `--samples` samples of 16 windows of 64 drawn
  between batches (what a learner reads).

Targets (issue 62, on an H200 with the Warp humanoid 8192 x 200): the collector at least 0.95x
the dataset's steps/s, and the collector with the buffer at least 0.9x (at most 10% of the
stream).

    python benchmarks/bench_torchrl.py --quick
    python benchmarks/bench_torchrl.py --backend warp --save --tag h200
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import common  # noqa: F401  (puts the checkout on the path)
import simloader
from simloader.torchrl import SimCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler


class Policy(torch.nn.Module):
    """A small MLP from the state to the controls, as an acting world-model policy."""

    def __init__(self, nstate: int, nu: int, dtype: torch.dtype):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(nstate, 64, dtype=dtype),
                                       torch.nn.Tanh(), torch.nn.Linear(64, nu, dtype=dtype))

    def forward(self, obs):
        return torch.tanh(self.net(obs["state"]))


def steps_per_second(batches, seconds: float, per_batch) -> float:
    """Steps per second of an iterable of batches after a warm-up one, for `seconds`;
    `per_batch(batch)` does the consumer's work and returns the batch's steps."""
    it = iter(batches)
    per_batch(next(it))
    common.sync()
    n, start = 0, time.perf_counter()
    for batch in it:
        n += per_batch(batch)
        common.sync()
        if time.perf_counter() - start >= seconds:
            break
    elapsed = time.perf_counter() - start
    close = getattr(it, "close", None)
    if close is not None:
        close()
    return n / elapsed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--backend", default="cpu", choices=("cpu", "mjx", "warp"))
    p.add_argument("--model", default="humanoid")
    p.add_argument("--nbatch", type=int, default=8192)
    p.add_argument("--nstep", type=int, default=200)
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--capacity", type=int, default=4_000_000, help="buffer rows")
    p.add_argument("--samples", type=int, default=1, help="16 x 64 samples between batches")
    common.add_output_options(p)
    args = p.parse_args()
    if args.quick:
        args.nbatch, args.nstep, args.seconds, args.repeats = 64, 100, 1.0, 1
        args.capacity = 50_000
    device = "cuda" if args.backend != "cpu" else None
    probe = simloader.SimDataset(args.model, backend=args.backend, nbatch=1, nstep=1,
                                 device=device)
    dtype = torch.float64 if args.backend == "cpu" else torch.float32
    policy = Policy(probe.config.nstate, probe.config.ncontrol, dtype)
    if device is not None:
        policy = policy.to(device)
    ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                              nstep=args.nstep, seed=0, policy=policy, device=device,
                              continue_episodes=True, prefetch=1)
    steps = args.nbatch * args.nstep

    def plain(batch) -> int:
        batch["state"].sum()  # touched
        return steps

    def tensordict(td) -> int:
        td["next", "observation"].sum()
        return steps

    buffer = ReplayBuffer(storage=LazyTensorStorage(args.capacity, device=device or "cpu"),
                          sampler=SliceSampler(slice_len=64, strict_length=True,
                                               traj_key=("collector", "traj_ids")),
                          batch_size=16 * 64)

    def buffered(td) -> int:
        buffer.extend(td[td["collector", "mask"]])
        for _ in range(args.samples):
            buffer.sample()["observation"].sum()
        return steps

    rates: dict[str, list[float]] = {"dataset": [], "collector": [], "collector + buffer": []}
    for _ in range(args.repeats):
        rates["dataset"].append(steps_per_second(
            torch.utils.data.DataLoader(ds, batch_size=None), args.seconds, plain))
        rates["collector"].append(steps_per_second(SimCollector(ds), args.seconds, tensordict))
        rates["collector + buffer"].append(steps_per_second(
            SimCollector(ds), args.seconds, buffered))
    base = statistics.median(rates["dataset"])
    targets = {"collector": "target >= 0.95x", "collector + buffer": "target >= 0.9x"}
    rows = [f"| {name} | {statistics.median(r) / 1e6:.3f}M | "
            f"{statistics.median(r) / base:.3f}x{'; ' + targets[name] if name in targets else ''}"
            f" |" for name, r in rates.items()]
    table = "\n".join([
        f"{args.model} {args.nbatch} x {args.nstep}, backend={args.backend!r}, a 2-layer MLP "
        f"policy in the loop, continue_episodes=True, prefetch=1; buffer: "
        f"LazyTensorStorage({args.capacity}) on {device or 'cpu'}, SliceSampler(64, "
        f"traj_key), {args.samples} sample(s) of 16 x 64 between batches; medians of "
        f"{args.repeats} alternating repeats of {args.seconds} s each",
        "",
        "| consumer | steps/s | ratio to the dataset |",
        "| --- | --- | --- |", *rows])
    common.report(args, "bench_torchrl", "The torchrl collector against the dataset, steps "
                  "per second", [table])


if __name__ == "__main__":
    main()
