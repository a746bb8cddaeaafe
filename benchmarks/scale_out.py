"""Scale-out: the DDP world-model example under torchrun on 1, 2, ... GPUs, throughput vs 1.

Runs `torchrun --standalone --nproc_per_node=N examples/train_world_model_ddp.py` for each N of
`--nprocs` in turn (fresh processes each, the same per-rank work), reads the throughput rank 0
reports (simulated steps per second of all ranks together over the slowest rank's time, with
training) and prints it next to the first N's. Target: 2 GPUs at least 1.9x one GPU. NVLink
multicast stays off in NCCL (shared machines: see the device notes), whatever the caller's
environment says.

    python benchmarks/scale_out.py --nprocs 1 2 --save --results-dir $OUT     # on 2 GPUs
    python benchmarks/scale_out.py --quick --backend rollout                  # CPU smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import common

EXAMPLE = common.REPO / "examples" / "train_world_model_ddp.py"
TARGET = 1.9  # 2 GPUs / 1 GPU
SAFE_ENV = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1",
            "NVSHMEM_DISABLE_NVLS": "1"}


def run(nproc: int, example_args: list[str]) -> dict:
    """One torchrun job of `nproc` local ranks; rank 0's figures."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "result.json")
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                   f"--nproc_per_node={nproc}", str(EXAMPLE), *example_args, "--json", path]
        env = {**os.environ, **SAFE_ENV}
        proc = subprocess.run(command, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"{nproc} rank(s) failed ({proc.returncode}):\n"
                             f"{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
        print(proc.stdout.strip(), file=sys.stderr)
        with open(path) as f:
            return json.load(f)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--nprocs", type=int, nargs="+", default=[1, 2],
                   help="ranks (GPUs) of each run; the first is the reference")
    p.add_argument("--quick", action="store_true", help="the example's --quick sizes")
    p.add_argument("--backend", default="auto", choices=("auto", "rollout", "mjx"))
    p.add_argument("--batches", type=int, default=60, help="batches per rank")
    p.add_argument("--nbatch", type=int, default=16384)
    p.add_argument("--nstep", type=int, default=100)
    p.add_argument("--minibatches", type=int, default=1,
                   help="optimizer steps per simulated batch (the example's default is 4; "
                        "fewer keeps the simulation the larger part of the time)")
    p.add_argument("--save", action="store_true")
    p.add_argument("--results-dir", type=common.pathlib.Path,
                   default=common.REPO / "benchmarks" / "results")
    p.add_argument("--tag", default="")
    args = p.parse_args()
    example_args = ["--backend", args.backend] + (["--quick"] if args.quick else [
        "--batches", str(args.batches), "--nbatch", str(args.nbatch), "--nstep", str(args.nstep),
        "--minibatches", str(args.minibatches)])

    rows, reference = [], None
    for nproc in common.progress(args.nprocs, desc="torchrun jobs"):
        r = run(nproc, example_args)
        reference = reference or r["steps_per_s"]
        rows.append([nproc, r["backend"], r["device"], f"{r['nbatch']} x {r['nstep']}",
                     r["timed_batches_per_rank"], f"{r['steps_per_s'] / 1e6:,.2f}M",
                     f"{r['simulate_only_steps_per_s'] / 1e6:,.2f}M",
                     f"{r['steps_per_s'] / reference:.2f}x"])
    headers = ["ranks", "backend", "device", "per-rank batch", "timed batches per rank",
               "steps/s (with training)", "steps/s (simulation time only)",
               f"vs {args.nprocs[0]} rank(s)"]
    table = common.markdown_table(headers, rows)
    notes = (f"Each row is one torchrun job of the DDP world-model example (one process per "
             f"GPU, each simulating its own stream, DDP gradients over NCCL); steps/s is all "
             f"ranks' simulated steps over the slowest rank's time after a warm-up of 5 "
             f"batches, training included. Target: 2 ranks >= {TARGET}x 1 rank.")
    common.report(args, "scale_out", "DDP world-model example: throughput vs ranks",
                  [notes, table])


if __name__ == "__main__":
    main()
