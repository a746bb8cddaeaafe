"""Several simulation GPUs, one delivery GPU: steps/s delivered on cuda:0 fed by K GPUs.

For each engine of `--engines` (`mjx`: MJX on JAX; `warp`: MuJoCo Warp) and each K of `--sims`,
one `SimDataset(device="cuda:0", sim_device=["cuda:1", ..., "cuda:K"])` whose batch is K times
the per-GPU workload (`--per-gpu`): its trajectories are split across the K simulation GPUs
and delivered, gathered, on cuda:0. A light consumer (the sum of the batch's states on cuda:0,
waited for) takes `--batches` batches after a warm-up batch; the steps/s delivered on cuda:0
are reported against K = 1 in the same run, and against the baseline row "same GPU"
(`sim_device=None`: the per-GPU workload simulated on cuda:0 itself). `--repeats` runs,
alternating the configurations; the median is reported. An engine refusing a configuration
(`sim_device` not supported, say) is a row saying so.

Target (issue: several GPUs): K = 3 at least 2.85x K = 1. It needs K + 1 GPUs: cuda:0 delivers,
cuda:1..K simulate; Ks that do not fit are left out, with a message. It cannot run without a
GPU.

    python benchmarks/sim_devices.py --save --results-dir $OUT                   # on 4 GPUs
    python benchmarks/sim_devices.py --engines warp --sims 1 2 3 --per-gpu warp=humanoid:8192x100
"""

from __future__ import annotations

import os

# JAX must not take 75% of every GPU up front: torch gathers the batches on cuda:0
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Optional  # noqa: E402

import torch  # noqa: E402

import common  # noqa: E402
import simloader  # noqa: E402

PER_GPU = {"warp": common.Workload("humanoid", 8192, 200),
           "mjx": common.Workload("cartpole", 8192, 1000)}
TARGET = {3: 2.85}  # K: steps/s delivered at least this times K = 1
DELIVER = "cuda:0"


def parse_per_gpu(text: str) -> tuple[str, common.Workload]:
    """`warp=humanoid:8192x200` -> ("warp", Workload("humanoid", 8192, 200)) (for argparse)."""
    engine, sep, workload = text.partition("=")
    if not sep or engine not in PER_GPU:
        raise argparse.ArgumentTypeError(f"expected ENGINE=MODEL:NBATCHxNSTEP with ENGINE one of "
                                         f"{sorted(PER_GPU)}, got {text!r}")
    return engine, common.parse_workload(workload)


def dataset(engine: str, w: common.Workload, k: Optional[int],
            args: argparse.Namespace) -> simloader.SimDataset:
    """The per-GPU workload `w` on cuda:0 (k None), or k times it simulated on cuda:1..k."""
    model = common.load_model(w.name, args.model_dir)
    extra = {} if k is None else {"sim_device": [f"cuda:{i}" for i in range(1, k + 1)]}
    return simloader.SimDataset(model, backend=engine, nbatch=w.nbatch * (k or 1),
                                nstep=w.nstep, control=simloader.controls.Uniform(),
                                seed=args.seed, device=DELIVER, **extra)


def measure(ds: simloader.SimDataset, nbatches: int) -> float:
    """Seconds for `nbatches` batches after a warm-up batch, each summed on cuda:0 and waited
    for (a fresh iterator: its producer starts with it and stops at the end)."""
    it = iter(ds)
    try:
        batch = next(it)  # warm-up: compilation, graph capture, threads
        batch["state"].sum()
        common.sync()
        start = time.perf_counter()
        for _ in range(nbatches):
            del batch  # release a multi-GB batch before the next arrives
            batch = next(it)
            batch["state"].sum()  # the consumer: touches every state on cuda:0
            common.sync()
        return time.perf_counter() - start
    finally:
        it.close()
        common.drain()  # the batches dispatched ahead must not slow what is timed next


def run(engine: str, w: common.Workload, ks: list[int],
        args: argparse.Namespace) -> list[list[str]]:
    """The rows of one engine: "same GPU", then every K."""
    configs: dict = {"same GPU": None, **{k: k for k in ks}}
    sets, rows, refused = {}, {}, {}
    for name, k in configs.items():
        try:
            sets[name] = dataset(engine, w, k, args)
        except (ValueError, TypeError) as e:  # the engine refuses this configuration
            refused[name] = str(e).splitlines()[0][:160]
    times: dict = {name: [] for name in sets}
    order = list(sets)
    for rep in common.progress(range(args.repeats), desc=engine):
        for name in order if rep % 2 == 0 else reversed(order):
            times[name].append(measure(sets[name], args.batches))
    rates = {}
    for name, t in times.items():
        k = configs[name] or 1
        rates[name] = args.batches * w.nbatch * k * w.nstep / statistics.median(t)
    one, same = rates.get(1), rates.get("same GPU")
    for name, k in configs.items():
        sims = "cuda:0 (same GPU)" if k is None else ", ".join(f"cuda:{i}"
                                                                  for i in range(1, k + 1))
        label = "same GPU" if k is None else str(k)
        if name in refused:
            rows[name] = [engine, str(w), label, sims, "refused: " + refused[name],
                          "", "", "", ""]
            continue
        rate = rates[name]
        target = TARGET.get(k) if k else None
        vs_one = rate / one if one and k else None
        verdict = ("-" if target is None else
                   f">= {target}x: " + ("?" if vs_one is None else
                                        "yes" if vs_one >= target else "NO"))
        rows[name] = [engine, str(w), label, sims, f"{w.nbatch * (k or 1)} x {w.nstep}",
                      common.rate(rate), (f"{vs_one:.2f}x" if vs_one else "-"),
                      f"{rate / same:.2f}x" if same else "-", verdict]
    return list(rows.values())


HEADERS = ["engine", "workload per GPU", "K (simulation GPUs)", "simulated on",
           "batch delivered on cuda:0", "steps/s delivered", "vs K = 1", "vs same GPU",
           "target"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--engines", nargs="+", choices=list(PER_GPU), default=["mjx", "warp"])
    p.add_argument("--sims", type=int, nargs="+", default=[1, 2, 3],
                   help="simulation GPUs K (cuda:1..K) per configuration")
    p.add_argument("--per-gpu", nargs="+", type=parse_per_gpu, default=[],
                   metavar="ENGINE=MODEL:NBATCHxNSTEP",
                   help="the workload each simulation GPU takes (default: "
                        + " ".join(f"{e}={w}" for e, w in PER_GPU.items()) + ")")
    p.add_argument("--batches", type=int, default=8, help="timed batches after a warm-up batch")
    p.add_argument("--repeats", type=int, default=1,
                   help="timed runs of each configuration, alternating (the median is reported)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model-dir", type=common.pathlib.Path,
                   help="folder of the MJCF files (default: the repository's models)")
    common.add_output_options(p)
    args = p.parse_args()
    if args.batches < 1 or args.repeats < 1 or any(k < 1 for k in args.sims):
        p.error("--batches, --repeats and every --sims must be at least 1")
    if not torch.cuda.is_available():
        raise SystemExit("sim_devices.py needs GPUs (cuda:0 delivers, cuda:1..K simulate): "
                         "torch sees none on this machine")
    ngpu = torch.cuda.device_count()
    ks = sorted({k for k in args.sims if k + 1 <= ngpu})
    left = sorted(set(args.sims) - set(ks))
    if left:
        print(f"{ngpu} GPU(s): K = {left} left out (K simulation GPUs need K + 1)",
              file=sys.stderr)
    per_gpu = {**PER_GPU, **dict(args.per_gpu)}

    table = []
    for engine in args.engines:
        table += run(engine, per_gpu[engine], ks, args)
    notes = (f"One delivery GPU (cuda:0) fed by K simulation GPUs (cuda:1..K, "
             f"`SimDataset(device=\"cuda:0\", sim_device=[...])`, nbatch = K x the per-GPU "
             f"nbatch); \"same GPU\": the per-GPU workload simulated on cuda:0 "
             f"(`sim_device=None`). Steps/s delivered: {args.batches} batches after a warm-up "
             f"batch, each summed on cuda:0 and waited for; median of {args.repeats} run(s). "
             f"Target: K = 3 at least 2.85x K = 1. GPUs: {torch.cuda.get_device_name(0)} x "
             f"{ngpu}.")
    common.report(args, "sim_devices", "Several simulation GPUs feeding one delivery GPU",
                  [notes, common.markdown_table(HEADERS, table)])


if __name__ == "__main__":
    main()
