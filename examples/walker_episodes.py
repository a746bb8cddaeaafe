"""A walker world model trained on episodes that end where the task ends.

Random controls topple the dm_control walker within a few tenths of a second, so a stream of
fixed-length trajectories is mostly "lying on the floor". With `terminate=` an episode ends
when the torso falls below a height (or after a time limit), and the trajectory restarts from
a fresh initial state on the next frame (autoreset), as MuJoCo Playground or Isaac Lab
environments do. This example:

1. measures how much of each stream is the walker standing (torso above the limit), with and
   without the rule;
2. trains a one-step dynamics model on the episodic stream, pairing each frame only with the
   frame after it when that one is not a fresh start (`batch["first"]`);
3. reports the held-out one-step error and plots the torso heights each stream shows.

    python examples/walker_episodes.py            # a minute or two on a laptop's CPU
    python examples/walker_episodes.py --quick    # seconds, as the test suite runs it
"""

import argparse
import pathlib

import torch
from torch import nn

import simloader
from simloader import controls, initial
from simloader import terminate as T

WALKER = pathlib.Path(__file__).parent / "models" / "walker" / "walker.xml"
HEIGHT = 0.9  # the torso's height below which the walker counts as fallen (standing: 1.3)


def stream(nbatch, nstep, episodes, seed, backend):
    rules = [T.Below("torso", HEIGHT), T.TimeLimit(400)] if episodes else None
    return simloader.SimDataset(
        str(WALKER), nbatch=nbatch, nstep=nstep, seed=seed, backend=backend,
        control=controls.OrnsteinUhlenbeck(std=0.5, tau=0.1),
        initial_state=initial.Perturbed(qpos_std=0.02, qvel_std=0.1),
        continue_episodes=True, terminate=rules)


def pairs(batch):
    """(s_t, a_t, s_t+1) of the batch's steps that are physics: the state without its time
    column, never a frame paired with the fresh start after it, no diverged trajectory."""
    s = batch["state"][..., 1:].float()
    before = torch.cat([batch["initial_state"][:, None, 1:].float(), s[:, :-1]], dim=1)
    keep = ~batch["diverged"][:, None]
    if "first" in batch:
        keep = keep & ~batch["first"]
    return before[keep], batch["control"].float()[keep], s[keep]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--backend", default="auto")
    p.add_argument("--out", default="walker_episodes.png")
    args = p.parse_args()
    nbatch, nstep, batches = (16, 100, 6) if args.quick else (256, 200, 60)

    # 1. how much of each stream is the walker standing
    heights = {}
    for name, episodes in (("fixed-length trajectories", False), ("terminate=, autoreset", True)):
        ds = stream(nbatch, nstep, episodes, seed=0, backend=args.backend)
        torso = []
        for _, batch in zip(range(max(2, batches // 4)), ds):
            torso.append(batch.view("qpos", "rootz")[..., 0].flatten() + 1.3)
        heights[name] = torch.cat(torso)
        standing = (heights[name] >= HEIGHT).float().mean()
        print(f"{name}: {100 * standing:.0f}% of frames standing (torso >= {HEIGHT} m)")

    # 2. a one-step model on the episodic stream
    ds = stream(nbatch, nstep, True, seed=1, backend=args.backend)
    nq = ds.config.model.nq + ds.config.model.nv
    net = nn.Sequential(nn.Linear(nq + ds.config.model.nu, 256), nn.SiLU(),
                        nn.Linear(256, 256), nn.SiLU(), nn.Linear(256, nq))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    scale = None
    resets = 0
    for step, batch in zip(range(batches), ds):
        s, a, s1 = pairs(batch)
        resets += int(batch["first"].sum())
        if scale is None:
            scale = (s1 - s).std(0) + 1e-6
        loss = nn.functional.mse_loss(net(torch.cat([s, a], 1)), (s1 - s) / scale)
        opt.zero_grad()
        loss.backward()
        opt.step()
    print(f"trained on {batches} batches ({resets} resets); last loss {loss.item():.3f}")

    # 3. held out: another seed
    held = next(iter(stream(nbatch, nstep, True, seed=99, backend=args.backend)))
    s, a, s1 = pairs(held)
    with torch.no_grad():
        error = ((net(torch.cat([s, a], 1)) - (s1 - s) / scale) ** 2).mean()
    print(f"held-out one-step error (standardized): {error.item():.3f} over {len(s)} pairs")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for name, h in heights.items():
        ax.hist(h.numpy(), bins=40, range=(0, 1.6), alpha=0.6, label=name, density=True)
    ax.axvline(HEIGHT, color="k", lw=0.8, ls="--")
    ax.set_xlabel("torso height (m)")
    ax.set_ylabel("share of frames")
    ax.set_title("What the walker streams show")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"plot: {args.out}")


if __name__ == "__main__":
    main()
