"""The `simloader` command line: `quickstart` (stream batches, print throughput), `info` (what
the columns mean), `bench` (simloader next to the raw simulators) and `warmup` (compile ahead of
time: JAX's persistent compilation cache and MuJoCo Warp's kernel cache)."""

from __future__ import annotations

import argparse
import time

import mujoco
import torch
from tqdm import tqdm

import simloader
from simloader import observe, sharding

def parse_control_spec(text: str) -> int:
    """`ctrl|xfrc_applied` or an integer bitmask (`simloader.layout.parse_control_spec`)."""
    try:
        return simloader.layout.parse_control_spec(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def quickstart(args: argparse.Namespace) -> None:
    ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                              nstep=args.nstep, control=simloader.controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(),
                              num_batches=args.batches, seed=args.seed,
                              # all cores: nothing here trains alongside the simulation
                              nthread=sharding.available_cpus())
    loader = torch.utils.data.DataLoader(ds, batch_size=None)
    print(f"simloader {simloader.__version__}: model {args.model!r}, backend "
          f"{ds.config.backend!r}, {args.nbatch} trajectories x {args.nstep} steps per batch")
    steps, start, first = 0, time.perf_counter(), None
    for batch in tqdm(loader, total=args.batches, unit="batch"):
        if first is None:  # the first batch includes start-up (and compilation for MJX)
            first = time.perf_counter() - start
            start = time.perf_counter()
            shapes = {k: tuple(v.shape) for k, v in batch.items()}
        else:
            steps += batch["state"].shape[0] * batch["state"].shape[1]
        diverged = int(batch["diverged"].sum())
        if diverged:
            tqdm.write(f"{diverged} trajectories diverged in this batch")
    elapsed = time.perf_counter() - start
    print(f"batch tensors: {shapes}")
    print(f"first batch after {first:.2f} s (start-up included)")
    if steps:
        print(f"throughput: {steps / elapsed:,.0f} steps/s ({elapsed * 1e9 / steps:,.0f} ns/step) "
              f"over {args.batches - 1} batches")


def info(args: argparse.Namespace) -> None:
    print(simloader.describe(args.model, args.control_spec))
    if args.record:
        model = simloader.load_model(args.model)
        observations = observe.parse(model, [name.strip() for name in args.record.split(",")])
        print("recorded keys (nbatch, nframes, ...) and their named parts:")
        print(simloader.layout.BatchLayout(model, args.control_spec, observations).describe())


def bench(args: argparse.Namespace) -> None:
    from simloader import bench as b
    model = simloader.load_model(args.model)
    backends = args.backends or (["rollout", "mjx"] if b.jax_has_gpu() else ["rollout"])
    name = args.model if len(args.model) < 40 else "model"
    w = b.Workload(name, args.nbatch, args.nstep)
    print(f"simloader {simloader.__version__} bench: {w} on {', '.join(backends)}, median of "
          f"{args.repeats} alternating repetitions")
    s_per_step, runs_on, notes = b.compare(
        model, w, backends, repeats=args.repeats, min_seconds=args.min_seconds,
        python_steps=args.python_steps, seed=args.seed)
    print(b.markdown_table(b.HEADERS, b.method_rows(w, s_per_step, runs_on, b.RAW_OF, b.PYTHON)))
    for note in notes:
        print(note)
    if args.plot:
        b.bar_plot(args.plot, f"{w}: simloader vs raw", s_per_step)
        print(f"plot saved to {args.plot}")


def warmup(args: argparse.Namespace) -> None:
    """Simulates one batch of the configuration, which fills the persistent caches (JAX's
    compiled batch function for these sizes; MuJoCo Warp's kernels for this model, which take
    about a minute to compile the first time on a machine), so that later processes start in
    seconds."""
    start = time.perf_counter()
    ds = simloader.SimDataset(args.model, backend="mjx", impl=args.impl, nbatch=args.nbatch,
                              nstep=args.nstep, control=simloader.controls.Uniform(),
                              num_batches=1)
    print(ds.describe().splitlines()[-1])
    next(iter(ds))
    print(f"warm: compiled in {ds.stats['compile_s']:.1f} s, first batch after "
          f"{time.perf_counter() - start:.1f} s; later processes reuse the caches")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="simloader", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    q = sub.add_parser("quickstart", help="stream batches from a model and print throughput")
    q.add_argument("--model", default="cartpole",
                   help="built-in model name or MJCF/MJB path (default: the built-in cartpole)")
    q.add_argument("--backend", default="auto", choices=("auto", "rollout", "mjx"))
    q.add_argument("--nbatch", type=int, default=1024)
    q.add_argument("--nstep", type=int, default=200)
    q.add_argument("--batches", type=int, default=20)
    q.add_argument("--seed", type=int, default=0)
    q.set_defaults(run=quickstart)

    i = sub.add_parser("info", help="print which state/control/sensor columns mean what")
    i.add_argument("model", help="built-in model name or MJCF/MJB path")
    i.add_argument("--control-spec", type=parse_control_spec,
                   default=int(mujoco.mjtState.mjSTATE_CTRL),
                   help="components of the control vector, e.g. 'ctrl|xfrc_applied' (default ctrl)")
    i.add_argument("--record", default="",
                   help="names to record, e.g. 'qpos,xpos,sensor:tip_pos': what each key holds")
    i.set_defaults(run=info)

    b = sub.add_parser("bench", help="time simloader's backends next to the raw simulators")
    b.add_argument("model", nargs="?", default="cartpole",
                   help="built-in model name or MJCF/MJB path (default: the built-in cartpole)")
    b.add_argument("--backends", nargs="+", choices=("rollout", "mjx"),
                   help="default: rollout, and mjx where JAX sees a GPU")
    b.add_argument("--nbatch", type=int, default=1024)
    b.add_argument("--nstep", type=int, default=200)
    b.add_argument("--repeats", type=int, default=3, help="alternating timed repetitions")
    b.add_argument("--min-seconds", type=float, default=2.0,
                   help="each timed repetition lasts at least this long")
    b.add_argument("--python-steps", type=int, default=5000,
                   help="steps of the single-environment Python loop per repetition")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--plot", default="simloader-bench.png",
                   help="where to save the bar chart ('' for none)")
    b.set_defaults(run=bench)

    w = sub.add_parser("warmup", help="compile the MJX backend for a model ahead of time")
    w.add_argument("model", help="built-in model name or MJCF/MJB path")
    w.add_argument("--impl", default="auto", choices=("auto", "jax", "warp"))
    w.add_argument("--nbatch", type=int, default=1024,
                   help="trajectories per batch, as the training run will use them")
    w.add_argument("--nstep", type=int, default=200, help="steps per batch, as in training")
    w.set_defaults(run=warmup)

    args = parser.parse_args(argv)
    args.run(args)


if __name__ == "__main__":
    main()
