"""One stream over several processes, one per GPU, as a user runs it under `torchrun`: the
suite's `ranks` side (`workloads.RANKS`).

`job(stream, ranks, ...)` starts `torchrun --standalone --nproc_per_node=RANKS -m
simloader.bench.ranks`; each rank (this module's `main`) builds the stream's `SimDataset` (its
device: the rank's GPU, `cuda:LOCAL_RANK`, which every engine picks under torchrun; the CPU
without one), takes a warm-up batch (compilation, graph capture), waits for the others, times
`batches` batches, and rank 0 writes what all ranks measured: their steps per second together
(every rank's steps over the slowest rank's seconds) and per GPU, and whether the ranks drew
distinct batches (one seeded stream split by rank, not one stream repeated).
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time
from typing import Any

from simloader.bench import startup
from simloader.bench.workloads import Stream

SPEC = "SIMLOADER_BENCH_RANKS"  # the job's spec (JSON) in each rank's environment
# NVLink multicast off in NCCL: shared machines refuse it (the device notes)
NCCL_SAFE_ENV = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1",
                 "NVSHMEM_DISABLE_NVLS": "1"}
# and one OpenMP thread a rank whatever the ranks (torchrun sets it only for more than one)
SAFE_ENV = {**NCCL_SAFE_ENV, "OMP_NUM_THREADS": "1"}
STOP_S = 30.0  # seconds torchrun gets to stop its ranks after a timeout


def job(stream: Stream, ranks: int, batches: int, seed: int, timeout: float) -> dict[str, Any]:
    """One torchrun job of `ranks` processes streaming `stream` (each rank `stream.nbatch`
    trajectories a batch): {"steps_per_s", "per_gpu", "per_rank", "distinct", "devices"}.

    Raises:
      RuntimeError: the job failed or timed out (its output's tail).
    """
    with tempfile.TemporaryDirectory(prefix="simloader-ranks-") as folder:
        out = pathlib.Path(folder) / "ranks.json"
        env = dict(os.environ, **SAFE_ENV)
        env[SPEC] = json.dumps({"stream": dataclasses.asdict(stream), "batches": batches,
                                "seed": seed, "out": str(out)})
        env["PYTHONPATH"] = startup.pythonpath(env.get("PYTHONPATH", ""))
        command = [sys.executable, "-m", "torch.distributed.run", "--standalone",
                   f"--nproc_per_node={ranks}", "-m", "simloader.bench.ranks"]
        proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        try:
            output, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            # torchrun starts its ranks in sessions of their own: killing it alone would leave
            # them holding the GPUs; SIGTERM makes it stop them, then it is killed
            proc.terminate()
            try:
                output, _ = proc.communicate(timeout=STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                output, _ = proc.communicate()
            raise RuntimeError(f"{ranks} ranks of {stream}: timed out after {timeout:.0f} s\n"
                               f"{(output or '')[-3000:]}") from None
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"{ranks} ranks of {stream}: exit {proc.returncode}\n"
                               f"{output[-3000:]}")
        return json.loads(out.read_text())


def main() -> None:
    """One rank of a `job` (run by torchrun)."""
    import hashlib

    import torch
    import torch.distributed as dist

    import simloader
    from simloader.bench import datasets

    spec = json.loads(os.environ[SPEC])
    fields: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v
                              for k, v in spec["stream"].items()}  # JSON lists: tuples
    stream = Stream(**fields)
    gpu = torch.cuda.is_available()
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if gpu:
        torch.cuda.set_device(local)
    dist.init_process_group("nccl" if gpu else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    model = simloader.load_model(stream.model)
    ds = datasets.dataset(stream, model, spec["seed"])
    it = iter(ds)
    first = next(it)  # compilation, graph capture, threads
    digest = hashlib.sha256(first["control"].detach().cpu().numpy().tobytes()).hexdigest()
    device = str(first["control"].device)
    dist.barrier()
    start = time.perf_counter()
    for _ in range(spec["batches"]):
        next(it)
        if gpu:
            torch.cuda.current_stream().synchronize()
    seconds = time.perf_counter() - start
    it.close()
    results: list[Any] = [None] * world
    dist.all_gather_object(results, {"seconds": seconds, "digest": digest, "device": device})
    if rank == 0:
        steps = spec["batches"] * stream.steps
        together = world * steps / max(r["seconds"] for r in results)
        pathlib.Path(spec["out"]).write_text(json.dumps({
            "steps_per_s": together, "per_gpu": together / world,
            "per_rank": [steps / r["seconds"] for r in results],
            "distinct": len({r["digest"] for r in results}) == world,
            "devices": [r["device"] for r in results]}))
    dist.destroy_process_group()


if __name__ == "__main__":
    main()
