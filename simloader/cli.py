"""The `simloader` command line: `quickstart` (stream batches, print throughput) and `info`."""

from __future__ import annotations

import argparse
import time

import mujoco
import torch
from tqdm import tqdm

import simloader

_SPEC_NAMES = {c.lower(): int(getattr(mujoco.mjtState, f"mjSTATE_{c}"))
               for c in ("CTRL", "QFRC_APPLIED", "XFRC_APPLIED", "EQ_ACTIVE", "MOCAP_POS",
                         "MOCAP_QUAT", "USERDATA")}


def parse_control_spec(text: str) -> int:
    """`ctrl|xfrc_applied` or an integer bitmask."""
    if text.isdigit():
        return int(text)
    try:
        return sum(_SPEC_NAMES[part.strip().lower()] for part in text.split("|"))
    except KeyError as e:
        raise argparse.ArgumentTypeError(
            f"unknown control_spec component {e.args[0]!r}; known: {sorted(_SPEC_NAMES)}") from None


def quickstart(args: argparse.Namespace) -> None:
    ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                              nstep=args.nstep, control=simloader.controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(),
                              num_batches=args.batches, seed=args.seed)
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
    model = simloader.load_model(args.model)
    print(simloader.describe(model, args.control_spec))


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
    i.add_argument("--control-spec", type=parse_control_spec, default=_SPEC_NAMES["ctrl"],
                   help="components of the control vector, e.g. 'ctrl|xfrc_applied' (default ctrl)")
    i.set_defaults(run=info)

    args = parser.parse_args(argv)
    args.run(args)


if __name__ == "__main__":
    main()
