"""The cart-pole world model under torchrun: one process per GPU, each simulating its own data.

Every rank builds the same `SimDataset`; simloader reads the rank from torch.distributed and
draws that rank's own stream of the one seed (no two ranks see the same trajectory), simulates
on the rank's GPU (`cuda:LOCAL_RANK`, with JAX restricted to it) or on the rank's share of the
CPU cores, and DistributedDataParallel averages the gradients. `--batches` is per rank.

    torchrun --standalone --nproc_per_node=2 examples/train_world_model_ddp.py
    torchrun --nnodes=2 --nproc_per_node=8 --rdzv-backend=c10d --rdzv-endpoint=HOST:29400 \\
        examples/train_world_model_ddp.py                         # across machines
    python examples/train_world_model_ddp.py --quick             # one process, as CI runs it

Rank 0 prints the simulation throughput of all ranks together (`--json` also writes it, for
benchmarks/scale_out.py) and the held-out prediction errors.
"""

import argparse
import gc
import json
import os
import time

import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from train_world_model import evaluate, setup, transitions


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--batches", type=int, default=200, help="batches per rank")
    parser.add_argument("--nbatch", type=int, default=4096, help="trajectories per batch")
    parser.add_argument("--nstep", type=int, default=100)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--minibatches", type=int, default=4,
                        help="optimizer steps per simulated batch (on random transitions)")
    parser.add_argument("--warmup", type=int, default=5,
                        help="batches before the throughput clock starts (compilation)")
    parser.add_argument("--json", help="rank 0 writes the throughput figures here")
    args = parser.parse_args()
    if args.quick:
        args.batches, args.nbatch, args.nstep, args.width, args.warmup = 12, 64, 60, 64, 2

    # torchrun sets RANK/WORLD_SIZE/LOCAL_RANK; run plainly, this is one process of one
    distributed = "WORLD_SIZE" in os.environ
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if torch.cuda.is_available():
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    else:
        device = torch.device("cpu")
    if distributed:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    rank = dist.get_rank() if distributed else 0
    world = dist.get_world_size() if distributed else 1

    backend, train, held_out, net, physics = setup(args, device)
    ddp = nn.parallel.DistributedDataParallel(net) if distributed else net
    opt = torch.optim.Adam(ddp.parameters(), lr=1e-3)
    if rank == 0:
        print(f"{world} rank(s), backend {backend} on {device.type}: {args.batches} batches of "
              f"{args.nbatch} x {args.nstep} per rank")

    transitions_per_batch = args.nbatch * args.nstep
    minibatch = max(1, transitions_per_batch // 16)
    steps, clock = 0, None
    loader = torch.utils.data.DataLoader(train, batch_size=None)
    for i, batch in enumerate(tqdm(loader, total=args.batches, disable=rank != 0)):
        if i == args.warmup:  # from here on every rank is compiled and streaming
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            clock = time.perf_counter()
        elif clock is not None:
            steps += args.nbatch * args.nstep
        s, a, s_next = transitions(batch, physics)
        # diverged trajectories are masked, not dropped: every rank must take the same number
        # of optimizer steps, or DDP's gradient all-reduce waits forever
        keep = (~batch["diverged"]).repeat_interleave(args.nstep).float()
        for _ in range(args.minibatches):
            pick = torch.randint(transitions_per_batch, (minibatch,), device=device)
            error = (ddp(s[pick], a[pick]) - s_next[pick]) / net.delta_std
            loss = (error.pow(2).mean(-1) * keep[pick]).sum() / keep[pick].sum().clamp_min(1)
            opt.zero_grad()
            loss.backward()
            opt.step()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elapsed = time.perf_counter() - clock if clock is not None else float("nan")

    # all ranks' steps over the slowest rank's time: the job's throughput
    figures = torch.tensor([steps, elapsed, train.stats["steps"], train.stats["simulate_s"]],
                           dtype=torch.float64, device=device)
    if distributed:
        total = figures.clone()
        dist.all_reduce(total, op=dist.ReduceOp.SUM)
        slowest = figures.clone()
        dist.all_reduce(slowest, op=dist.ReduceOp.MAX)
    else:
        total = slowest = figures
    if rank == 0:
        result = {
            "ranks": world, "backend": backend, "device": str(device.type),
            "nbatch": args.nbatch, "nstep": args.nstep, "timed_batches_per_rank":
                args.batches - args.warmup - 1,
            "steps_per_s": total[0].item() / slowest[1].item(),
            # the simulation's own time (ds.stats): all ranks' steps over the slowest rank's
            "simulate_only_steps_per_s": total[2].item() / max(slowest[3].item(), 1e-12),
        }
        print(f"throughput, training included: {result['steps_per_s']:,.0f} simulated steps/s "
              f"over {world} rank(s)")
        if args.json:
            with open(args.json, "w") as f:
                json.dump(result, f)
        evaluate(net, held_out, physics)
    if distributed:
        # DDP's reducer holds the process group (and gloo's worker threads): dropped first, so
        # that destroying the group joins those threads now, not when the interpreter tears
        # the module down at exit (where a thread still joinable aborts the process:
        # "terminate called without an active exception", about one run in three)
        del ddp, opt
        gc.collect()
        dist.destroy_process_group()


if __name__ == "__main__":
    main()
