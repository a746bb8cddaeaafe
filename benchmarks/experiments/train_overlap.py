"""Does training wait for simloader? The share of a training loop's wall time spent on data.

A torch MLP learns the state change of a step from (state, control) on every batch of a
`SimDataset`, on the device the batches are delivered to. First simulation alone and one
optimizer step alone are timed; then the optimizer steps per batch are chosen so that training
on a batch takes `--slack` times as long as simulating one. The loop then trains on `--batches`
batches after a warm-up batch, and the time blocked in `next(iterator)` (plus the wait for the
batch's device work) is the waiting time; the fraction of wall time it takes should stay under
5% (performance.md, target 3), as simloader simulates the next batch while one is trained on.

Next to the waiting share, the overlap as the issue defines it: (train alone + simulate
alone - wall time per batch in the loop) / min(train alone, simulate alone): 1 when the
simulation is fully hidden behind the training, 0 when the two run one after the other.

Backend cpu simulates on the CPU (trains on `--device`: the GPU when there is one, with
the cores split between simulation and torch otherwise); mjx and warp simulate and train on
the GPU of `--device`. There the two share one GPU: where the training keeps the GPU busy, the
times measured alone add up rather than overlap, and only the GPU time training leaves idle
hides simulation. So on a GPU two MLP sizes run by default, one whose steps leave the GPU mostly
idle and one that keeps it busy (`--mlp`). With `--sim-device` (one GPU or several) the GPU
engines also run simulating there (`SimDataset(sim_device=...)`), the batches delivered to
`--device` where the MLP trains: rows "same GPU" and "other GPU" side by side.

Default workloads: cpu and mjx cart-pole 8192 x 1000, warp humanoid 8192 x 100 (`--workloads`
replaces them for every backend).

    python benchmarks/experiments/train_overlap.py --quick
    python benchmarks/experiments/train_overlap.py --backends cpu mjx warp --save --results-dir $OUT
    python benchmarks/experiments/train_overlap.py --device cuda:0 --sim-device cuda:1 --save \\
        --results-dir $OUT --tag other-gpu                                   # on 2 GPUs
"""

from __future__ import annotations

import os

# torch trains on the GPU JAX simulates on: JAX must not take 75% of it up front
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from typing import Optional  # noqa: E402

import torch  # noqa: E402

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
import simloader  # noqa: E402

DEFAULTS = {"cpu": [common.Workload("cartpole", 8192, 1000)],
            "mjx": [common.Workload("cartpole", 8192, 1000)],
            "warp": [common.Workload("humanoid", 8192, 100)]}
QUICK = [common.Workload("cartpole", 256, 100)]
GPU_ENGINES = ("mjx", "warp")
TARGET = 0.05  # fraction of wall time waiting for data


class Trainer:
    """An MLP predicting `state[t] - state[t-1]` from `(state[t-1], control[t])`."""

    def __init__(self, nstate: int, ncontrol: int, hidden: int, layers: int, minibatch: int,
                 device: torch.device, seed: int):
        torch.manual_seed(seed)
        sizes = [nstate + ncontrol] + [hidden] * layers
        blocks = []
        for a, b in zip(sizes[:-1], sizes[1:]):
            blocks += [torch.nn.Linear(a, b), torch.nn.ReLU()]
        self.net = torch.nn.Sequential(*blocks, torch.nn.Linear(sizes[-1], nstate)).to(device)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-3)
        self.minibatch = minibatch
        self.device = device

    def train(self, batch: dict[str, torch.Tensor], nsteps: int) -> float:
        """`nsteps` optimizer steps on random minibatches of the batch's transitions."""
        state = batch["state"]
        prev = torch.cat([batch["initial_state"][:, None], state[:, :-1]], dim=1)
        x = torch.cat([prev, batch["control"]], dim=-1).flatten(0, 1)
        y = (state - prev).flatten(0, 1)
        for _ in range(nsteps):
            idx = torch.randint(x.shape[0], (self.minibatch,), device=self.device)
            loss = torch.nn.functional.mse_loss(self.net(x[idx]), y[idx])
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
        return loss.item()


def timed(fn, *args) -> float:
    common.sync()
    start = time.perf_counter()
    fn(*args)
    common.sync()
    return time.perf_counter() - start


def parse_mlp(text: str) -> tuple[int, int]:
    """`256x4096` -> (hidden width 256, minibatch 4096) (for argparse)."""
    try:
        hidden, minibatch = map(int, text.lower().split("x"))
        return hidden, minibatch
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HIDDENxMINIBATCH such as 256x4096, got "
                                         f"{text!r}") from None


def run(backend: str, w: common.Workload, args: argparse.Namespace,
        sim_device: Optional[list[str]] = None) -> list[list[str]]:
    """Times simulation alone, then per MLP size calibrates and runs the training loop
    `--repeats` times; one table row per MLP size. `sim_device`: the GPUs the engine
    simulates on (None: where the batches are delivered)."""
    options: dict = {"dtype": torch.float32}
    torch_threads = common.cpu_count()
    if backend == "cpu":
        options["device"] = args.device
        if args.device == "cpu":  # simulation and training share the cores
            options["nthread"] = args.sim_threads or max(1, torch_threads // 2)
            torch_threads = max(1, torch_threads - options["nthread"])
    elif backend == "warp" or sim_device:
        options["device"] = args.device
    if sim_device:
        options["sim_device"] = sim_device[0] if len(sim_device) == 1 else sim_device
    torch.set_num_threads(torch_threads)
    model = common.load_model(w.name, args.model_dir)
    ds = simloader.SimDataset(model, backend=backend, nbatch=w.nbatch, nstep=w.nstep,
                              control=simloader.controls.Uniform(), seed=args.seed, **options)
    calib = common.time_stream(ds, args.calibration_batches, keep_last=True)
    sim_s = calib.steady_s / args.calibration_batches
    batch = calib.last
    del calib
    device = batch["state"].device
    simulated_on = ("CPU" if backend == "cpu" else ", ".join(sim_device) if sim_device
                    else f"same GPU ({device})" if device.type == "cuda"
                    else f"same device ({device})")
    sizes = args.mlp or ([(256, 4096), (1024, 32768)] if device.type == "cuda" else [(128, 1024)])

    rows = []
    for hidden, minibatch in sizes:
        trainer = Trainer(ds.config.nstate, ds.config.ncontrol, hidden, args.layers, minibatch,
                          device, args.seed)
        trainer.train(batch, 5)  # warm-up
        opt_s = timed(trainer.train, batch, 20) / 20
        nsteps = max(1, math.ceil(args.slack * sim_s / opt_s))
        train_s = timed(trainer.train, batch, nsteps)
        if train_s < args.slack * sim_s:  # a batch costs more than its steps (features, noise)
            nsteps = math.ceil(nsteps * args.slack * sim_s / train_s)
            train_s = timed(trainer.train, batch, nsteps)
        first_loss = trainer.train(batch, 1)
        mlp = f"{args.layers} x {hidden}, minibatch {minibatch}"
        print(f"{backend} {w}, MLP {mlp}: simulate {sim_s:.3f} s/batch alone, train "
              f"{train_s:.3f} s/batch alone ({nsteps} optimizer steps of {opt_s * 1e3:.2f} ms)",
              file=sys.stderr)

        fractions, during, overlaps = [], [], []
        for _ in common.progress(range(args.repeats), desc=f"{backend} {w} {hidden}"):
            before = ds.stats
            waited, total, loss = overlap(ds, trainer, nsteps, args.batches)
            after = ds.stats
            fractions.append(waited / total)
            # batches trained on: the warm-up batch (its training is timed) and --batches more
            per_batch = total / (args.batches + 1)
            overlaps.append((train_s + sim_s - per_batch) / min(train_s, sim_s))
            # the mjx backend's simulate_s over-counts when the consumer is the slower side
            if backend == "cpu":
                during.append((after["simulate_s"] - before["simulate_s"])
                              / (after["batches"] - before["batches"]))
        fraction = statistics.median(fractions)
        rows.append([backend, f"{w.name} {w.nbatch} x {w.nstep}", simulated_on, str(device),
                     mlp,
                     f"{sim_s:.3f}", f"{train_s:.3f}", f"{train_s / sim_s:.2f}", nsteps,
                     f"{statistics.median(during):.3f}" if during else "-",
                     f"{100 * fraction:.2f}%", f"{100 * max(fractions):.2f}%",
                     "yes" if fraction < TARGET else "NO",
                     f"{statistics.median(overlaps):.2f}", f"{first_loss:.3g} -> {loss:.3g}"])
    return rows


def overlap(ds: simloader.SimDataset, trainer: Trainer, nsteps: int,
            nbatches: int) -> tuple[float, float, float]:
    """Seconds waiting for data, seconds in all, and the last loss, over `nbatches` batches.

    The clock starts when the first batch (threads, compilation) is in hand. Before each
    `next` the device is synchronized, so the training's queued work counts as training, and
    after it again, so data still being produced or copied counts as waiting.
    """
    it = iter(ds)
    try:
        batch = next(it)
        common.sync()
        start, waited = time.perf_counter(), 0.0
        loss = trainer.train(batch, nsteps)
        for _ in range(nbatches):
            common.sync()
            t = time.perf_counter()
            del batch
            batch = next(it)
            common.sync()
            waited += time.perf_counter() - t
            loss = trainer.train(batch, nsteps)
        common.sync()
        return waited, time.perf_counter() - start, loss
    finally:
        it.close()
        common.drain()  # the batches dispatched ahead must not slow what is timed next


HEADERS = ["backend", "workload", "simulated on", "trains on", "MLP",
           "simulate s/batch (alone)", "train s/batch (alone)", "train / simulate",
           "optimizer steps per batch", "simulate s/batch (while training, cpu)",
           "waiting (median)", "waiting (max)", "< 5%", "overlap (median)", "loss"]


def default_backends() -> list[str]:
    """mjx and warp on a GPU; cpu without one."""
    return list(GPU_ENGINES) if torch.cuda.is_available() else ["cpu"]


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], [w for ws in DEFAULTS.values() for w in ws],
                      QUICK)
    for action in p._actions:  # the defaults are per backend
        if action.dest == "workloads":
            action.help = ("what to run, for every backend (default: "
                           + "; ".join(f"{b} {' '.join(map(str, ws))}"
                                       for b, ws in DEFAULTS.items()) + ")")
    p.add_argument("--backends", nargs="+", choices=("cpu", "mjx", "warp"),
                   help="default: mjx and warp on a GPU, cpu without one")
    p.add_argument("--batches", type=int, default=None,
                   help="batches trained on after the warm-up batch (default 10, --quick 5)")
    p.add_argument("--calibration-batches", type=int, default=3,
                   help="batches timed to measure simulation alone")
    p.add_argument("--slack", type=float, default=1.5,
                   help="training time per batch / simulation time per batch")
    p.add_argument("--mlp", nargs="+", type=parse_mlp, metavar="HIDDENxMINIBATCH",
                   help="MLP widths and transitions per optimizer step, one row each (default "
                        "on a GPU: 256x4096, whose steps leave the GPU mostly idle, and "
                        "1024x32768, which keeps it busy; on the CPU: 128x1024)")
    p.add_argument("--layers", type=int, default=3, help="hidden layers")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu",
                   help="where the batches are delivered and the MLP trains (mjx without "
                        "--sim-device: JAX's device)")
    p.add_argument("--sim-device", nargs="+", metavar="DEVICE",
                   help="GPU(s) where mjx and warp simulate as well (SimDataset sim_device=), "
                        "delivering to --device: rows for the same GPU and for these")
    p.add_argument("--sim-threads", type=int,
                   help="CPU engine threads when training on the CPU (default: half the cores)")
    args = p.parse_args()
    args.batches = args.batches or (5 if args.quick else 10)

    table = []
    for backend in args.backends or default_backends():
        placements = [None] + ([args.sim_device] if args.sim_device and backend in GPU_ENGINES
                               else [])
        for w in common.workloads(args, DEFAULTS[backend], QUICK):
            for sim_device in placements:
                try:
                    table += run(backend, w, args, sim_device)
                except (ValueError, TypeError) as e:  # the engine refuses the combination
                    if sim_device is None:
                        raise
                    table.append([backend, f"{w.name} {w.nbatch} x {w.nstep}",
                                  ", ".join(sim_device),
                                  "refused: " + str(e).splitlines()[0][:160]]
                                 + [""] * (len(HEADERS) - 4))

    text = common.markdown_table(HEADERS, table)
    notes = (f"Waiting: time in next(iterator) and the device sync after it, as a share of the "
             f"wall time of {args.batches} batches of training after a warm-up batch; median and "
             f"max of {args.repeats} runs. Training is set to take {args.slack}x the simulation "
             f"time of a batch (both measured alone first). Target: waiting < 5%. Overlap: (train "
             f"alone + simulate alone - wall time per batch in the loop) / min(train alone, "
             f"simulate alone), median of the runs: 1 = simulation fully hidden, 0 = serial.")
    common.report(args, "train_overlap", "Training while simloader simulates", [notes, text])


if __name__ == "__main__":
    main()
