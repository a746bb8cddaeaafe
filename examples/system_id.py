"""System identification: recover a cart-pole's pole mass and length from its trajectories.

The pole's mass and length are randomized per trajectory (structural variants: the length
changes the geometry, so each variant is compiled from the MjSpec, and MuJoCo derives the
inertia); a torch model reads a trajectory's states and controls and predicts both. Reports the
relative error on held-out trajectories.

    python examples/system_id.py [--quick]
"""

import argparse
import time

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader import controls
from simloader import randomize as dr

MASS, LENGTH = (0.05, 0.3), (0.5, 1.5)


def pole_variant(spec, rng):
    mass, length = rng.uniform(*MASS), rng.uniform(*LENGTH)
    spec.geom("pole").mass = mass
    spec.geom("pole").fromto = [0, 0, 0, 0, 0, length]
    spec.site("tip").pos = [0, 0, length]
    return spec


def targets(pool):
    """(count, 2): each variant's true pole mass and length."""
    return torch.tensor([[m.body("pole").mass[0], 2 * m.geom("pole").size[1]] for m in pool],
                        dtype=torch.float32)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--backend", default="cpu", choices=("auto", "cpu", "mjx", "warp"))
    args = parser.parse_args()
    nvariant, nbatch, nstep, batches = (32, 64, 40, 20) if args.quick else (512, 512, 100, 300)

    common = dict(backend=args.backend, nbatch=nbatch, nstep=nstep, dtype=torch.float32,
                  control=controls.OrnsteinUhlenbeck(std=0.7, tau=0.1),
                  initial_state=simloader.initial.Perturbed(qpos_std=0.2, qvel_std=0.2),
                  randomize=dr.Variants(pole_variant, count=nvariant))
    train = simloader.SimDataset("cartpole", num_batches=batches, seed=0, **common)
    held_out = simloader.SimDataset("cartpole", seed=1, **common)  # its own pool of variants
    test = next(iter(held_out))
    truth = targets(train.config.variants)
    low, high = torch.tensor([MASS[0], LENGTH[0]]), torch.tensor([MASS[1], LENGTH[1]])

    def features(batch):
        x = torch.cat([batch["state"][..., 1:], batch["control"]], -1)  # drop time
        return x.flatten(1)

    def labels(batch):  # normalized to [0, 1]
        return (truth[batch["params"]["variant"]] - low) / (high - low)

    width = features(test).shape[1]
    net = nn.Sequential(nn.Linear(width, 256), nn.SiLU(), nn.Linear(256, 256), nn.SiLU(),
                        nn.Linear(256, 2))
    center, scale = features(test).mean(0), features(test).std(0).clamp_min(1e-3)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    start = time.perf_counter()
    for batch in tqdm(torch.utils.data.DataLoader(train, batch_size=None), total=batches):
        keep = ~batch["diverged"]
        x, y = (features(batch)[keep] - center) / scale, labels(batch)[keep]
        for _ in range(2):  # two epochs of minibatches over every fresh batch
            for chunk in torch.randperm(len(x)).split(64):
                loss = nn.functional.mse_loss(net(x[chunk]), y[chunk])
                opt.zero_grad()
                loss.backward()
                opt.step()
    print(f"trained on {batches} batches of {nbatch} trajectories ({nvariant} variants) in "
          f"{time.perf_counter() - start:.1f} s")
    with torch.no_grad():
        pred = net((features(test) - center) / scale) * (high - low) + low
    true = targets(held_out.config.variants)[test["params"]["variant"]]
    rel = ((pred - true).abs() / true).mean(0)
    print(f"held-out mean relative error: pole mass {rel[0]:.1%}, pole length {rel[1]:.1%} "
          f"(guessing the range's middle: "
          f"{((true - (low + high) / 2).abs() / true).mean(0)[0]:.1%}, "
          f"{((true - (low + high) / 2).abs() / true).mean(0)[1]:.1%})")


if __name__ == "__main__":
    main()
