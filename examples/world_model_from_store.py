"""Generate a humanoid corpus once, then train a world model on it from disk, epoch after epoch.

The first run simulates `--batches` batches of the humanoid under smooth random controls into
a zarr store (`simloader.write`: resumable, readable by any zarr client, every trajectory
regenerable from its provenance); later runs find the store and skip straight to training.
Training reads `(s_t, a_t, s_t+1)` transitions from the store
(`StoredDataset.transitions().loader(...)`, shuffled across the whole corpus, `--workers`
reading)
for `--epochs` epochs, and the model is judged, as in `train_world_model.py`, on held-out
trajectories simulated fresh: one-step and open-loop errors, with a plot of predicted against
simulated trajectories.

    python examples/world_model_from_store.py                 # generate once, then train
    python examples/world_model_from_store.py --epochs 20     # train again, no simulation
    python examples/world_model_from_store.py --quick         # a few seconds, as CI runs it
"""

import argparse
import os
import tempfile
import time

import torch
from tqdm import tqdm

import simloader
from simloader import controls
from train_world_model import Dynamics, evaluate, plot_open_loop, transitions

HORIZON = 20
# plotted coordinates of qpos: the root's height and two joints (humanoid.xml's order)
PLOTTED = {"root height": 2, "right hip (y)": 9, "left knee": 16}


def stream(args, **kwargs):
    return simloader.SimDataset("humanoid", backend=args.backend, dtype=torch.float32,
                                control=controls.OrnsteinUhlenbeck(std=0.4, tau=0.2),
                                initial_state=simloader.initial.Perturbed(qpos_std=0.05,
                                                                          qvel_std=0.2),
                                record=("state",), **kwargs)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--store", help="the corpus (default outputs/humanoid-corpus.zarr; "
                                        "--quick: a temporary folder)")
    parser.add_argument("--batches", type=int, default=40, help="batches in the corpus")
    parser.add_argument("--nbatch", type=int, default=256)
    parser.add_argument("--nstep", type=int, default=100)
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--batch-size", type=int, default=4096, help="transitions per step")
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--workers", type=int, default=2, help="DataLoader workers reading")
    parser.add_argument("--out", default="outputs/world_model_from_store.png",
                        help="where to save the plot (outputs/ is git-ignored)")
    args = parser.parse_args()
    scratch = None
    if args.quick:
        args.batches, args.nbatch, args.nstep, args.epochs, args.width = 3, 16, 20, 2, 64
        args.batch_size, args.workers = 256, 0
        if args.store is None:
            scratch = tempfile.TemporaryDirectory()
            args.store = os.path.join(scratch.name, "humanoid-corpus.zarr")
    args.store = args.store or "outputs/humanoid-corpus.zarr"

    # 1. the corpus, generated once (an interrupted run resumes; a finished one is kept)
    corpus = stream(args, nbatch=args.nbatch, nstep=args.nstep, seed=0)
    start = time.perf_counter()
    simloader.write(corpus, args.store, batches=args.batches)
    print(f"corpus: {args.store}, {args.batches} x {args.nbatch} humanoid trajectories of "
          f"{args.nstep} steps ({time.perf_counter() - start:.1f} s to generate or find)")

    # 2. training from disk, several epochs over the same transitions
    stored = simloader.StoredDataset(args.store)
    model = corpus.model
    physics = slice(1, 1 + model.nq + model.nv)  # drop time, the state's first column
    device = "cuda" if torch.cuda.is_available() else "cpu"
    held_out = next(iter(stream(args, nbatch=32, nstep=HORIZON, seed=1)))  # never stored
    held_out = {k: v.to(device) for k, v in held_out.items()}
    net = Dynamics(model.nq + model.nv, model.nu, args.width).to(device)
    train = stored.transitions()
    # inputs and changes normalized over the corpus it trains on (a sample of it)
    sample = train.gather(torch.randint(len(train), (min(len(train), 65536),)).numpy())
    net.fit_normalization(sample["state"][:, physics].to(device), sample["control"].to(device),
                          sample["next/state"][:, physics].to(device))
    loader = train.loader(args.batch_size, num_workers=args.workers,
                          persistent_workers=args.workers > 0, drop_last=True)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.epochs * len(loader))
    # transitions() leaves out the trajectories flagged diverged: never learn non-physics
    print(f"training on {len(train):,} stored transitions "
          f"({int(stored.flagged().sum())} diverged trajectories left out), {args.epochs} "
          f"epochs, {device}")
    start = time.perf_counter()
    for epoch in range(args.epochs):
        progress = tqdm(loader, desc=f"epoch {epoch + 1}/{args.epochs}")
        for batch in progress:
            loss = net.loss(batch["state"].to(device)[:, physics],
                            batch["control"].to(device),
                            batch["next/state"].to(device)[:, physics])
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            progress.set_postfix(loss=f"{loss.item():.2e}")
    print(f"trained in {time.perf_counter() - start:.1f} s")

    truth, pred, err = evaluate(net, held_out, physics)

    plot_open_loop(truth, pred, PLOTTED, model.opt.timestep,
                   f"humanoid world model trained from a store ({args.epochs} epochs), "
                   f"{HORIZON}-step open-loop RMSE {err[-1].item():.2e}", args.out)
    if scratch is not None:
        scratch.cleanup()


if __name__ == "__main__":
    main()
