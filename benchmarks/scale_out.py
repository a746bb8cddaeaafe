"""Scale-out: every engine under torchrun, one process per GPU, throughput against one GPU.

For each engine (`cpu`: MuJoCo on the CPU; `mjx`: MJX on JAX; `warp`: MuJoCo Warp), mode and
number of ranks of `--nprocs`, one `torchrun --standalone --nproc_per_node=N` job of this script
in its child role: each rank streams its own part of one seeded stream on its own GPU
(`cuda:LOCAL_RANK`; the CPU without one) and times `--batches` batches after a warm-up batch.
The modes:

- `open`: open-loop uniform controls, state and sensors of every step;
- `camera`: the same with a 64x64 RGB camera;
- `policy`: a torch MLP (2x256) on the rank's device chooses every step's controls;
- `write`: every rank writes its slots of one store (`simloader.write`), timed until written;
- `ddp`: the DDP world-model example (`examples/train_world_model_ddp.py`), training included
  (engines `cpu` and `mjx`: the example chooses its MJX implementation itself).

A row reports the steps/s of all ranks together (all ranks' steps over the slowest rank's
time), per rank, and against the first `--nprocs` in the same run; and two checks of the
stream: every rank's first batch differs from every other's (seeds by global rank), and
simulating that batch again from (seed, rank, batch index) gives it again (bit for bit on
the CPU backend; on a GPU, the same initial states and controls and states within 1e-3).
A combination an engine refuses (a camera on MJX-JAX, say) is a row saying so.

Targets (issue: several GPUs): 2 GPUs at least 1.95x one for Warp humanoid 8192 per GPU and
JAX cart-pole; 4 GPUs at least 3.8x. NVLink multicast stays off in NCCL (shared machines).

    python benchmarks/scale_out.py --nprocs 1 2 --save --results-dir $OUT        # on 2 GPUs
    python benchmarks/scale_out.py --quick --engines cpu --nprocs 1 2         # CPU smoke run
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time

import common

EXAMPLE = common.REPO / "examples" / "train_world_model_ddp.py"
SAFE_ENV = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1",
            "NVSHMEM_DISABLE_NVLS": "1"}
ENGINES = {"cpu": {"backend": "cpu"}, "mjx": {"backend": "mjx"}, "warp": {"backend": "warp"}}
MODES = ("open", "camera", "policy", "write", "ddp")
WORKLOADS = {"cpu": "cartpole:1024x100", "mjx": "cartpole:8192x1000",
             "warp": "humanoid:8192x200"}
QUICK = {"cpu": "cartpole:64x20", "mjx": "cartpole:64x20", "warp": "cartpole:64x20"}
QUICK_CAMERA = "cartpole:4x5"  # a CPU without a GPU renders about 30 frames/s
GPU_TOL = 1e-3  # a GPU batch simulated again: MuJoCo Warp's atomics may reorder sums
REFUSED = 3  # the child's exit status when the engine refuses the combination


# --------------------------------------------------------------------------- one rank

def _dataset(args, device):
    import torch
    import simloader
    w = common.parse_workload(args.workload)
    record = ["state", "sensordata"]
    if args.mode == "camera":
        record.append(simloader.Camera(-1, height=64, width=64))
    drive = {"control": simloader.controls.Uniform()}
    if args.mode == "policy":
        import mujoco
        model = simloader.load_model(w.name)
        nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)  # "state"
        mlp = torch.nn.Sequential(torch.nn.Linear(nstate, 256), torch.nn.Tanh(),
                                  torch.nn.Linear(256, 256), torch.nn.Tanh(),
                                  torch.nn.Linear(256, model.nu))
        dtype = torch.float64 if args.engine == "cpu" else torch.float32
        mlp = mlp.to(device=device, dtype=dtype)
        drive = {"policy": lambda obs: mlp(obs["state"])}
    return simloader.SimDataset(w.name, nbatch=w.nbatch, nstep=w.nstep, seed=args.seed,
                                record=tuple(record), device=device, **drive,
                                **ENGINES[args.engine])


def _digest(batch) -> str:
    h = hashlib.sha256()
    for key in ("initial_state", "control"):
        h.update(batch[key].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _again(ds, shard, index, batch) -> bool:
    """The rank's batch `index`, simulated again from its seed, equals `batch` (bit for bit
    on the CPU; on a GPU the same draws and states within GPU_TOL)."""
    import torch
    backend = ds.make_backend(shard)
    try:
        _, again, _ = next(iter(ds.stream(backend, [index])))
    finally:
        backend.close()
    if ds.config.backend == "cpu":
        return all(torch.equal(again[k], batch[k]) for k in batch if k != "params")
    return (torch.equal(again["initial_state"], batch["initial_state"]) and
            (again["state"] - batch["state"]).abs().max().item() <= GPU_TOL)


def child(args) -> None:
    """One rank of a torchrun job: its throughput and stream checks, gathered by rank 0."""
    import torch
    import torch.distributed as dist
    import simloader
    from simloader import sharding
    gpu = torch.cuda.is_available()
    local = int(os.environ.get("LOCAL_RANK", "0"))
    device = f"cuda:{local}" if gpu else "cpu"
    if gpu:
        torch.cuda.set_device(local)
    dist.init_process_group("nccl" if gpu else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    try:
        ds = _dataset(args, device)
    except (ValueError, TypeError) as e:  # the engine refuses this combination
        if rank == 0:
            with open(args.json, "w") as f:
                json.dump({"refused": str(e).splitlines()[0][:160]}, f)
        dist.destroy_process_group()
        raise SystemExit(REFUSED)
    w = ds.config
    shard = sharding.current_shard()
    it = iter(ds)
    first = next(it)  # warm-up: compilation, graph capture, threads
    digest, same = _digest(first), _again(ds, shard, 0, first)
    dist.barrier()
    start = time.perf_counter()
    if args.mode == "write":
        it.close()
        simloader.write(ds, args.store, batches=args.batches * world, progress=False)
    else:
        for _ in range(args.batches):
            next(it)
            if gpu:
                torch.cuda.current_stream().synchronize()
        it.close()
    seconds = time.perf_counter() - start
    results = [None] * world
    dist.all_gather_object(results, {"rank": rank, "seconds": seconds, "digest": digest,
                                     "again": same, "device": str(device)})
    if rank == 0:
        steps = args.batches * w.nbatch * w.nstep
        slowest = max(r["seconds"] for r in results)
        out = {"steps_per_s": world * steps / slowest,
               "per_rank": [steps / r["seconds"] for r in results],
               "distinct": len({r["digest"] for r in results}) == world,
               "reproducible": all(r["again"] for r in results),
               "device": torch.cuda.get_device_name(0) if gpu else "CPU"}
        if args.mode == "write":
            stored = simloader.StoredDataset(args.store)
            out["stored"] = len(stored)
            out["ranks_in_store"] = sorted({stored.provenance(i)["rank"]
                                            for i in range(0, len(stored), w.nbatch)})
        with open(args.json, "w") as f:
            json.dump(out, f)
    dist.destroy_process_group()


# --------------------------------------------------------------------------- the jobs

def run(nproc: int, args, engine: str, mode: str, workload: str) -> dict:
    """One torchrun job of `nproc` local ranks; rank 0's figures (or why it was refused)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "result.json")
        if mode == "ddp":
            w = common.parse_workload(workload)
            command = [str(EXAMPLE), "--backend", ENGINES[engine]["backend"]] + (
                ["--quick"] if args.quick else
                ["--batches", str(args.batches + 5), "--nbatch", str(w.nbatch),
                 "--nstep", str(w.nstep), "--minibatches", "1"])
        else:
            command = [__file__, "--child", "--engine", engine, "--mode", mode,
                       "--workload", workload, "--batches", str(args.batches),
                       "--seed", str(args.seed), "--store", os.path.join(tmp, "s.zarr")]
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                   f"--nproc_per_node={nproc}", *command, "--json", path]
        try:
            proc = subprocess.run(command, env={**os.environ, **SAFE_ENV}, capture_output=True,
                                  text=True, timeout=args.job_timeout)
        except subprocess.TimeoutExpired as e:
            raise SystemExit(f"{engine}/{mode} on {nproc} rank(s) ran past --job-timeout "
                             f"({args.job_timeout} s):\n{(e.stderr or b'')[-3000:]!r}")
        if proc.returncode != 0 and os.path.exists(path):
            with open(path) as f:
                refused = json.load(f)
            if "refused" in refused:
                return refused
        if proc.returncode != 0:
            raise SystemExit(f"{engine}/{mode} on {nproc} rank(s) failed ({proc.returncode}):"
                             f"\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
        with open(path) as f:
            return json.load(f)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--engine", help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    p.add_argument("--workload", help=argparse.SUPPRESS)
    p.add_argument("--store", help=argparse.SUPPRESS)
    p.add_argument("--json", help=argparse.SUPPRESS)
    p.add_argument("--engines", nargs="+", default=list(ENGINES), choices=list(ENGINES))
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--nprocs", type=int, nargs="+", default=[1, 2],
                   help="ranks (GPUs) of each job; the first is the reference")
    p.add_argument("--workloads", nargs="+", metavar="ENGINE=MODEL:NBATCHxNSTEP", default=[],
                   help=f"per-rank sizes (default {WORKLOADS}; --quick {QUICK['cpu']})")
    p.add_argument("--batches", type=int, default=8, help="timed batches per rank")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    p.add_argument("--job-timeout", type=float, default=900, help="seconds per torchrun job")
    p.add_argument("--save", action="store_true")
    p.add_argument("--results-dir", type=common.pathlib.Path,
                   default=common.REPO / "benchmarks" / "results")
    p.add_argument("--tag", default="")
    args = p.parse_args()
    if args.child:
        return child(args)
    sizes = {**(QUICK if args.quick else WORKLOADS),
             **dict(item.split("=", 1) for item in args.workloads)}

    rows = []
    jobs = [(e, m) for e in args.engines for m in args.modes if not (m == "ddp" and e == "warp")]
    for engine, mode in common.progress(jobs, desc="engines x modes"):
        reference = None
        for nproc in args.nprocs:
            workload = QUICK_CAMERA if args.quick and mode == "camera" else sizes[engine]
            r = run(nproc, args, engine, mode, workload)
            if "refused" in r:
                rows.append([engine, mode, workload, nproc, "refused: " + r["refused"],
                             "", "", "", ""])
                break
            reference = reference or r["steps_per_s"]
            per_rank = r.get("per_rank", [r["steps_per_s"] / nproc])
            checks = ("" if mode == "ddp" else
                      f"{'yes' if r['distinct'] else 'NO'} / {'yes' if r['reproducible'] else 'NO'}")
            if mode == "write":
                checks += f"; {r['stored']} stored, ranks {r['ranks_in_store']}"
            rows.append([engine, mode, workload, nproc, r["device"],
                         f"{r['steps_per_s'] / 1e6:.3g}M",
                         f"{min(per_rank) / 1e6:.3g}M", f"{r['steps_per_s'] / reference:.2f}x",
                         checks])
    headers = ["engine", "mode", "per-rank workload", "ranks", "device", "steps/s, all ranks",
               "slowest rank", f"vs {args.nprocs[0]} rank(s)",
               "streams distinct / reproducible"]
    notes = (f"Each row is one torchrun job, one process per GPU (or CPU processes without "
             f"GPUs), {args.batches} timed batches per rank after a warm-up batch; steps/s is "
             f"all ranks' steps over the slowest rank's time (`ddp`: the DDP example's own "
             f"figure, training included).")
    common.report(args, "scale_out", "Scale-out: engines under torchrun",
                  [notes, common.markdown_table(headers, rows)])


if __name__ == "__main__":
    main()
