"""Several simulation GPUs, one delivery GPU: steps/s delivered on cuda:0 fed by K GPUs.

For each engine of `--engines` (`mjx`: MJX on JAX; `warp`: MuJoCo Warp) and each K of `--sims`,
one `SimDataset(device="cuda:0", sim_device=["cuda:1", ..., "cuda:K"])` whose batch is K times
the per-GPU workload (`--per-gpu`): its trajectories are split across the K simulation GPUs
and delivered, gathered, on cuda:0. A consumer on cuda:0 takes `--batches` batches after a
warm-up: it sums the batch's states and, with `--train-ms` > 0, runs a fixed amount of GPU
work per batch standing in for a training step (a loop of 2048 x 2048 float32 matmuls on
cuda:0, its length calibrated once at start, on the idle GPU, to take about that many
milliseconds); each batch's work is waited for. The steps/s delivered on cuda:0 are reported
against K = 1 in the same run, and against the baseline row "same GPU" (`sim_device=None`:
the per-GPU workload simulated on cuda:0 itself), next to the trainer's waiting: the share of
the timed run spent waiting for batches (in `next()`, and on cuda:0 until the batch's copies
have landed there). With the default `--train-ms 0` the consumer is light and mostly waits;
the waiting is meaningful with a training step about as long as a batch's simulation.
`--repeats` runs, alternating the configurations; medians are reported. An engine refusing a
configuration (`sim_device` not supported, say) is a row saying so.

`--terminate`: every stream runs episodes, `terminate=` the model's rule (cart-pole: the
pole's hinge joint `Outside(..., -0.2, 0.2)`; humanoid: `Below("torso", 0.8)`).
`--mixture`: every configuration is a `simloader.Mixture` of two members with the same
`sim_device` split, sizes and engine, equal weights, one member's batch per delivered batch:
the workload, and the workload with another seed (`--mixture seed`, the default) or with
another seed and `terminate=` the model's rule (`--mixture terminate`); with `--terminate`
both members run episodes. The warm-up takes batches until both members have delivered one
(compiled).

Target (issue: several GPUs): K = 3 at least 2.85x K = 1, with the trainer waiting less than
5% of its time (checked where `--train-ms` > 0). It needs K + 1 GPUs: cuda:0 delivers,
cuda:1..K simulate; Ks that do not fit are left out, with a message. It cannot run without a
GPU.

    python benchmarks/sim_devices.py --save --results-dir $OUT                   # on 4 GPUs
    python benchmarks/sim_devices.py --engines warp --sims 1 2 3 --per-gpu warp=humanoid:8192x100
    python benchmarks/sim_devices.py --engines mjx --terminate --mixture --train-ms 200
"""

from __future__ import annotations

import os

# JAX must not take 75% of every GPU up front: torch gathers the batches on cuda:0
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Optional, Union  # noqa: E402

import mujoco  # noqa: E402
import torch  # noqa: E402

import common  # noqa: E402
import simloader  # noqa: E402
from simloader import terminate as T  # noqa: E402

PER_GPU = {"warp": common.Workload("humanoid", 8192, 200),
           "mjx": common.Workload("cartpole", 8192, 1000)}
TARGET = {3: 2.85}  # K: steps/s delivered at least this times K = 1
WAITING = 0.05  # ... with the trainer waiting less than this share of its time (--train-ms)
DELIVER = "cuda:0"
SIM_DEVICE = "cuda:{}"  # simulation device i (1..K), formatted
TRAIN_SIZE = 2048  # the training stand-in's square float32 matmuls


def _pole(model: mujoco.MjModel) -> T.Rule:
    """The cart-pole's pole: its (first) hinge joint, `hinge` in simloader's cartpole,
    `hinge_1` in dm_control's, outside [-0.2, 0.2] radians."""
    hinges = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(model.njnt)
              if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    if not hinges:
        raise SystemExit("--terminate: this cart-pole model has no hinge joint (the pole)")
    return T.Outside(hinges[0], -0.2, 0.2)


RULES = {"cartpole": _pole, "humanoid": lambda model: T.Below("torso", 0.8)}


def terminate_rule(name: str, model: mujoco.MjModel) -> T.Rule:
    """The `terminate=` rule of model `name` (`RULES`), for `--terminate` and `--mixture
    terminate`."""
    if name not in RULES:
        raise SystemExit(f"--terminate: no rule for model {name!r}; rules for {sorted(RULES)}")
    return RULES[name](model)


def parse_per_gpu(text: str) -> tuple[str, common.Workload]:
    """`warp=humanoid:8192x200` -> ("warp", Workload("humanoid", 8192, 200)) (for argparse)."""
    engine, sep, workload = text.partition("=")
    if not sep or engine not in PER_GPU:
        raise argparse.ArgumentTypeError(f"expected ENGINE=MODEL:NBATCHxNSTEP with ENGINE one of "
                                         f"{sorted(PER_GPU)}, got {text!r}")
    return engine, common.parse_workload(workload)


def dataset(engine: str, w: common.Workload, k: Optional[int], args: argparse.Namespace,
            seed: int, episodes: bool) -> simloader.SimDataset:
    """The per-GPU workload `w` on cuda:0 (k None), or k times it simulated on cuda:1..k;
    `episodes`: with `terminate=` the model's rule."""
    model = common.load_model(w.name, args.model_dir)
    extra = {} if k is None else {"sim_device": [SIM_DEVICE.format(i) for i in range(1, k + 1)]}
    if episodes:
        extra["terminate"] = terminate_rule(w.name, model)
    return simloader.SimDataset(model, backend=engine, nbatch=w.nbatch * (k or 1),
                                nstep=w.nstep, control=simloader.controls.Uniform(),
                                seed=seed, device=DELIVER, **extra)


Stream = Union[simloader.SimDataset, simloader.Mixture]


def stream(engine: str, w: common.Workload, k: Optional[int],
           args: argparse.Namespace) -> Stream:
    """A configuration's stream: the dataset, or with `--mixture` a Mixture of it and its
    second member (another seed; with `--mixture terminate` also `terminate=`)."""
    first = dataset(engine, w, k, args, args.seed, args.terminate)
    if not args.mixture:
        return first
    second = dataset(engine, w, k, args, args.seed + 1,
                     args.terminate or args.mixture == "terminate")
    return simloader.Mixture({"workload": first, args.mixture: second}, seed=args.seed)


def members(ds: Stream) -> int:
    return len(ds.datasets) if isinstance(ds, simloader.Mixture) else 1


def sync_delivery() -> None:
    """Waits for the work queued on the delivery device's current stream (named: the
    thread's current device is not assumed to be it)."""
    if torch.device(DELIVER).type == "cuda":
        torch.cuda.current_stream(torch.device(DELIVER)).synchronize()


class Trainer:
    """The consumer's fixed work per batch on the delivery device: `iterations` square
    float32 matmuls (none: the light consumer), after the sum of the batch's states."""

    def __init__(self, train_ms: float, device: str = DELIVER):
        self.iterations, self.ms = 0, 0.0
        if train_ms <= 0:
            return
        gen = torch.Generator(device).manual_seed(0)
        self.a = torch.randn(TRAIN_SIZE, TRAIN_SIZE, device=device, generator=gen)
        self.b = torch.randn(TRAIN_SIZE, TRAIN_SIZE, device=device, generator=gen) / TRAIN_SIZE
        # warm-up, then a probe of at least a second (a GPU idle before starts at low clocks)
        self.iterations = 10
        until = time.perf_counter() + 1.0
        while time.perf_counter() < until:
            self.work()
            sync_delivery()
        probe, start = 0, time.perf_counter()
        while time.perf_counter() - start < 1.0:
            self.work()
            sync_delivery()
            probe += self.iterations
        each = (time.perf_counter() - start) / probe
        self.iterations = max(1, round(train_ms / 1e3 / each))
        start = time.perf_counter()
        self.work()
        sync_delivery()
        self.ms = (time.perf_counter() - start) * 1e3

    def work(self) -> None:
        if not self.iterations:
            return
        x = self.a
        for _ in range(self.iterations):
            x = torch.mm(x, self.b)

    def __call__(self, batch: dict) -> None:
        batch["state"].sum()  # touches every state on the delivery device
        self.work()


def measure(ds: Stream, nbatches: int, trainer: Trainer) -> tuple[float, float]:
    """(seconds, seconds waiting) for `nbatches` batches after the warm-up (a batch, or with a
    Mixture batches until every member has delivered one), each consumed by `trainer` on
    cuda:0 and waited for; waiting: inside `next()` and until the batch's copies have landed
    on cuda:0 (a fresh iterator: its producers start with it and stop at the end)."""
    it = iter(ds)
    try:
        seen: set = set()
        for _ in range(50):  # warm-up: compilation, graph capture, threads, every member
            batch = next(it)
            seen.add(int(batch["task"]) if "task" in batch else 0)
            trainer(batch)
            sync_delivery()
            del batch  # release a multi-GB batch before the next arrives
            if len(seen) == members(ds):
                break
        waiting = 0.0
        start = time.perf_counter()
        for _ in range(nbatches):
            asked = time.perf_counter()
            batch = next(it)
            sync_delivery()  # the copies onto cuda:0 (the consumer's stream waits for them)
            waiting += time.perf_counter() - asked
            trainer(batch)
            sync_delivery()
            del batch
        return time.perf_counter() - start, waiting
    finally:
        it.close()
        common.drain()  # the batches dispatched ahead must not slow what is timed next


def run(engine: str, w: common.Workload, ks: list[int], args: argparse.Namespace,
        trainer: Trainer) -> list[list[str]]:
    """The rows of one engine: "same GPU", then every K."""
    configs: dict = {"same GPU": None, **{k: k for k in ks}}
    sets, rows, refused = {}, {}, {}
    for name, k in configs.items():
        try:
            sets[name] = stream(engine, w, k, args)
        except (ValueError, TypeError) as e:  # the engine refuses this configuration
            refused[name] = str(e).splitlines()[0][:160]
    times: dict = {name: [] for name in sets}
    waits: dict = {name: [] for name in sets}
    trains: dict = {name: [] for name in sets}  # ms per batch outside the waiting
    order = list(sets)
    for rep in common.progress(range(args.repeats), desc=engine):
        for name in order if rep % 2 == 0 else reversed(order):
            seconds, waiting = measure(sets[name], args.batches, trainer)
            times[name].append(seconds)
            waits[name].append(waiting / seconds)
            trains[name].append((seconds - waiting) / args.batches * 1e3)
    rates, waiting = {}, {}
    for name, t in times.items():
        k = configs[name] or 1
        rates[name] = args.batches * w.nbatch * k * w.nstep / statistics.median(t)
        waiting[name] = statistics.median(waits[name])
    one, same = rates.get(1), rates.get("same GPU")
    label_w = (str(w) + (" +terminate" if args.terminate else "")
               + (f" (Mixture: +{args.mixture})" if args.mixture else ""))
    for name, k in configs.items():
        sims = "cuda:0 (same GPU)" if k is None else ", ".join(f"cuda:{i}"
                                                                  for i in range(1, k + 1))
        label = "same GPU" if k is None else str(k)
        if name in refused:
            rows[name] = [engine, label_w, label, sims, "refused: " + refused[name],
                          "", "", "", "", "", ""]
            continue
        rate = rates[name]
        target = TARGET.get(k) if k else None
        vs_one = rate / one if one and k else None
        verdict = "-"
        if target is not None:
            wanted = f">= {target}x" + (f", waiting < {WAITING:.0%}" if trainer.iterations
                                         else "")
            met = vs_one is not None and vs_one >= target and (
                not trainer.iterations or waiting[name] < WAITING)
            verdict = f"{wanted}: " + ("?" if vs_one is None else "yes" if met else "NO")
        rows[name] = [engine, label_w, label, sims, f"{w.nbatch * (k or 1)} x {w.nstep}",
                      common.rate(rate), f"{waiting[name]:.1%}",
                      f"{statistics.median(trains[name]):.0f}",
                      (f"{vs_one:.2f}x" if vs_one else "-"),
                      f"{rate / same:.2f}x" if same else "-", verdict]
    return list(rows.values())


HEADERS = ["engine", "workload per GPU", "K (simulation GPUs)", "simulated on",
           "batch delivered on cuda:0", "steps/s delivered", "trainer waiting (% of time)",
           "consumer ms/batch",
           "vs K = 1", "vs same GPU", "target"]


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
    p.add_argument("--batches", type=int, default=8, help="timed batches after the warm-up")
    p.add_argument("--repeats", type=int, default=1,
                   help="timed runs of each configuration, alternating (the median is reported)")
    p.add_argument("--terminate", action="store_true",
                   help="episodes: terminate= the model's rule (" + ", ".join(
                       f"{m}: {r}" for m, r in (("cartpole", "Outside(<pole hinge>, -0.2, "
                                                 "0.2)"), ("humanoid", "Below('torso', 0.8)")))
                   + ")")
    p.add_argument("--mixture", nargs="?", const="seed", choices=["seed", "terminate"],
                   help="measure through a simloader.Mixture of two members with the same "
                        "sim_device split: the workload and the workload with seed + 1 "
                        "('seed'), or with seed + 1 and terminate= the model's rule "
                        "('terminate')")
    p.add_argument("--train-ms", type=float, default=0.0,
                   help="the consumer's fixed GPU work per batch on cuda:0, in milliseconds "
                        "(a matmul loop calibrated once at start); 0: only the sum of the "
                        "states (a light consumer)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model-dir", type=common.pathlib.Path,
                   help="folder of the MJCF files (default: the repository's models)")
    common.add_output_options(p)
    args = p.parse_args()
    if args.batches < 1 or args.repeats < 1 or any(k < 1 for k in args.sims):
        p.error("--batches, --repeats and every --sims must be at least 1")
    if args.train_ms < 0:
        p.error("--train-ms must be at least 0")
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
    if args.terminate or args.mixture == "terminate":  # a model without a rule: refused now
        for engine in args.engines:
            w = per_gpu[engine]
            terminate_rule(w.name, common.load_model(w.name, args.model_dir))
    trainer = Trainer(args.train_ms)
    if trainer.iterations:
        print(f"trainer: {trainer.iterations} matmuls of {TRAIN_SIZE} x {TRAIN_SIZE} per batch "
              f"on {DELIVER}, {trainer.ms:.1f} ms on the idle GPU", file=sys.stderr)

    table = []
    for engine in args.engines:
        table += run(engine, per_gpu[engine], ks, args, trainer)
    what = ""
    if args.terminate:
        rules = {e: terminate_rule(per_gpu[e].name, common.load_model(per_gpu[e].name,
                                                                      args.model_dir))
                 for e in args.engines}
        what = " Episodes: terminate= " + ", ".join(f"{e}: {r}" for e, r in rules.items()) + "."
    if args.mixture:
        what += (" Each configuration is a simloader.Mixture of two members with the same "
                 "split (equal weights, one member's batch per delivered batch): the "
                 "workload and the workload with seed + 1"
                 + (" and terminate= the model's rule" if args.mixture == "terminate" else "")
                 + "; the warm-up takes batches until both have delivered one.")
    consumer = ("summed on cuda:0 and waited for" if not trainer.iterations else
                f"summed on cuda:0, then {trainer.iterations} matmuls of {TRAIN_SIZE} x "
                f"{TRAIN_SIZE} float32 on cuda:0 ({trainer.ms:.1f} ms on the idle GPU; "
                f"--train-ms {args.train_ms:g}), waited for")
    notes = (f"One delivery GPU (cuda:0) fed by K simulation GPUs (cuda:1..K, "
             f"`SimDataset(device=\"cuda:0\", sim_device=[...])`, nbatch = K x the per-GPU "
             f"nbatch); \"same GPU\": the per-GPU workload simulated on cuda:0 "
             f"(`sim_device=None`).{what} Steps/s delivered: {args.batches} batches after a "
             f"warm-up, each {consumer}; trainer waiting: the share of the timed run spent in "
             f"next() and until the batch's copies have landed on cuda:0; medians of "
             f"{args.repeats} run(s). Target: K = 3 at least 2.85x K = 1"
             + (f", with the trainer waiting < {WAITING:.0%}" if trainer.iterations else "")
             + f". GPUs: {torch.cuda.get_device_name(0)} x {ngpu}.")
    common.report(args, "sim_devices", "Several simulation GPUs feeding one delivery GPU",
                  [notes, common.markdown_table(HEADERS, table)])


if __name__ == "__main__":
    main()
