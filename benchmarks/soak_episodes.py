"""Soak of episodes that end: a long stream with `continue_episodes=True` and a `TimeLimit`.

Streams `--batches` batches (at least 2,000 by default) of the built-in cart-pole with
`terminate=[Outside("hinge", -0.3, 0.3), TimeLimit(LIMIT)]` and episodes running across
batches, and checks while it runs:

- every fresh frame follows a terminated or truncated frame, in the same batch or at the end
  of the previous one (the flags of consecutive batches chain);
- no episode runs past the time limit: the steps since each trajectory's last fresh start,
  counted across batches, never exceed it;
- no fresh frame's control row was applied (NaN), every other one was (finite).

It reports the episodes completed, the resets, the terminations and truncations, and host
RSS at the start and the end (a sample every 250 batches).

    python benchmarks/soak_episodes.py --save                 # the CPU engine, 2,000 batches
    python benchmarks/soak_episodes.py --backend warp --save  # on a GPU
"""

from __future__ import annotations

import os
import time

import torch

import common
from common import markdown_table

import simloader
from simloader import controls
from simloader import terminate as T

LIMIT = 150


def host_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], [], [], repeats=False)
    p.add_argument("--backend", default="cpu")
    p.add_argument("--batches", type=int, default=2000)
    p.add_argument("--nbatch", type=int, default=256)
    p.add_argument("--nstep", type=int, default=100)
    args = common.parse(p)
    if args.quick:
        args.batches, args.nbatch = 50, 16
    ds = simloader.SimDataset("cartpole", nbatch=args.nbatch, nstep=args.nstep, seed=args.seed,
                              backend=args.backend, control=controls.Uniform(),
                              continue_episodes=True, num_batches=args.batches,
                              terminate=[T.Outside("hinge", -0.3, 0.3), T.TimeLimit(LIMIT)])
    n = args.nbatch
    since = torch.zeros(n, dtype=torch.int64)  # steps since each trajectory's fresh start
    ended_last = torch.zeros(n, dtype=torch.bool)  # the previous batch's last frame ended
    counts = dict(resets=0, terminated=0, truncated=0, steps=0)
    samples = [(0, host_rss_mb())]
    start = time.perf_counter()
    for i, batch in enumerate(common.progress(ds, desc="soak", total=args.batches), start=1):
        b = {k: v.cpu() for k, v in batch.items() if isinstance(v, torch.Tensor)}
        first, term, trunc = b["first"], b["terminated"], b["truncated"]
        ended = term | trunc
        # the flags chain across batches: a fresh frame follows an ending frame, and only then
        chained = torch.cat([ended_last[:, None], ended[:, :-1]], dim=1)
        assert torch.equal(first, chained), f"batch {i}: fresh frames not after ending ones"
        ended_last = ended[:, -1].clone()
        nan = torch.isnan(b["control"]).any(dim=-1)
        assert torch.equal(nan, first), f"batch {i}: a fresh frame's control was applied"
        for j in range(args.nstep):
            since = torch.where(first[:, j], 0, since + 1)
            assert int(since.max()) <= LIMIT, f"batch {i}: an episode ran past the time limit"
        counts["resets"] += int(first.sum())
        counts["terminated"] += int(term.sum())
        counts["truncated"] += int(trunc.sum())
        counts["steps"] += b["state"].shape[0] * b["state"].shape[1]
        if i % 250 == 0 or i == args.batches:
            samples.append((i, host_rss_mb()))
    seconds = time.perf_counter() - start
    episodes = counts["resets"]  # each reset closes one episode
    rows = [
        ["batches", f"{args.batches:,}"],
        ["steps", f"{counts['steps']:,}"],
        ["episodes completed (resets)", f"{episodes:,}"],
        ["ended by the rule (terminated) / by the time limit (truncated)",
         f"{counts['terminated']:,} / {counts['truncated']:,}"],
        ["mean episode length", f"{counts['steps'] / max(episodes, 1):.1f} steps"],
        ["checks", "fresh frames chain after ending ones across batches; no episode past "
                   f"{LIMIT} steps; fresh frames' controls NaN, all others finite"],
        ["host RSS at the start / at the end", f"{samples[0][1]:.0f} MB / {samples[-1][1]:.0f} MB"],
        ["host RSS samples (batch: MB)", ", ".join(f"{b}: {m:.0f}" for b, m in samples)],
        ["wall time", f"{seconds:.0f} s ({counts['steps'] / seconds / 1e6:.2f}M steps/s with "
                      f"the checks)"],
    ]
    sections = [f"`SimDataset('cartpole', nbatch={args.nbatch}, nstep={args.nstep}, "
                f"backend={args.backend!r}, continue_episodes=True, "
                f"terminate=[Outside('hinge', -0.3, 0.3), TimeLimit({LIMIT})])`, "
                f"{args.batches} batches in one process:",
                markdown_table(["", ""], rows)]
    common.report(args, "soak_episodes", "A long stream of episodes that end", sections)


if __name__ == "__main__":
    main()
