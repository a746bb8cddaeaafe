"""Online world-model training on torchrl, DreamerV3's loop: act, buffer, learn in
imagination, push the weights back.

A `SimCollector` streams the cart-pole acted by a small policy (with exploration noise) as
TensorDicts in torchrl's keys. Each batch's physics steps go to a torchrl
`ReplayBuffer(LazyTensorStorage(...), sampler=SliceSampler(traj_key=("collector",
"traj_ids")))`, whose windows never straddle two trajectories (episodes end when the pole
leans past 0.3 rad and continue across batches). At a train ratio of a few updates per batch:
a world model learns the dynamics from windows (predicting each window open loop from its
first frame, through its actions), and the policy learns in imagination, rolled out through
the world model from replayed states to keep the pole upright. `update_policy_weights_`
hands the new weights to the simulation; each batch names the version it acted with. The
plot shows the world model's loss and how long episodes last as the policy learns.

    python examples/online_torchrl.py            # about a minute on a 2-core CPU
    python examples/online_torchrl.py --quick    # seconds, as CI runs it
"""

import argparse
import os

import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader.terminate import Outside
from simloader.torchrl import SimCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler


def observed(state: torch.Tensor) -> torch.Tensor:
    """(x, theta, x_dot, theta_dot) of the cart-pole's full-physics state (time dropped)."""
    return state[..., 1:]


class Actor(nn.Module):
    """Observation -> the cart's force in [-1, 1]."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(4, 32), nn.Tanh(), nn.Linear(32, 1))

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(obs))

    def forward(self, obs: dict) -> torch.Tensor:  # what the simulation calls
        return self.act(observed(obs["state"]).to(self.net[0].weight.dtype))


class WorldModel(nn.Module):
    """(observation, action) -> the next observation, as a learned change."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(5, 128), nn.SiLU(), nn.Linear(128, 128), nn.SiLU(),
                                 nn.Linear(128, 4))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return obs + 0.05 * self.net(torch.cat([obs, action], -1))


def open_loop(model: WorldModel, windows) -> torch.Tensor:
    """Each window predicted from its first observation through its actions: mean squared
    error against the simulated frames."""
    obs = observed(windows["observation"][:, 0]).float()
    error = 0.0
    for t in range(windows.shape[1]):
        obs = model(obs, windows["action"][:, t].float())
        error = error + (obs - observed(windows["next", "observation"][:, t]).float()).pow(2).mean()
    return error / windows.shape[1]


def imagined(model: WorldModel, actor: Actor, starts: torch.Tensor, horizon: int) -> torch.Tensor:
    """The policy's cost rolled out through the world model: the pole's lean and the cart's
    distance from the middle, summed over `horizon` imagined steps."""
    obs, cost = starts, 0.0
    for _ in range(horizon):
        obs = model(obs, actor.act(obs))
        cost = cost + obs[:, 1].pow(2) + 0.05 * obs[:, 0].pow(2)
    return cost.mean() / horizon


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, seconds")
    parser.add_argument("--batches", type=int, default=60, help="batches collected")
    parser.add_argument("--ratio", type=int, default=8, help="updates per batch collected")
    parser.add_argument("--length", type=int, default=16, help="steps per replayed window")
    parser.add_argument("--out", default="outputs/online_torchrl.png",
                        help="where to save the plot (outputs/ is git-ignored)")
    args = parser.parse_args()
    nbatch, nstep, windows = 32, 50, 64
    if args.quick:
        args.batches, args.ratio, nbatch, windows = 4, 2, 8, 8
    torch.manual_seed(0)
    acting = Actor().double()  # the simulation's copy, brought up to date by the collector
    learner = Actor()
    acting.load_state_dict({k: v.double() for k, v in learner.state_dict().items()})
    ds = simloader.SimDataset(
        "cartpole", backend="cpu", nbatch=nbatch, nstep=nstep, policy=acting,
        policy_noise=simloader.controls.Normal(std=0.3), prefetch=1, continue_episodes=True,
        initial_state=simloader.initial.Perturbed(), seed=0,
        terminate=Outside("hinge", -0.3, 0.3))
    collector = SimCollector(ds, total_frames=args.batches * nbatch * nstep)
    rb = ReplayBuffer(storage=LazyTensorStorage(200_000),
                      sampler=SliceSampler(slice_len=args.length, strict_length=True,
                                           traj_key=("collector", "traj_ids")),
                      batch_size=windows * args.length)
    model = WorldModel()
    model_opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    actor_opt = torch.optim.Adam(learner.parameters(), lr=1e-3)
    losses, episode_lengths = [], []
    for td in tqdm(collector, total=len(collector), desc="collect + train"):
        ended = int(td["next", "done"].sum())  # steps per episode ended (all, if none did)
        episode_lengths.append(td.numel() / max(ended, 1))
        rb.extend(td[td["collector", "mask"]])
        if len(rb) < 4 * args.length * windows:
            continue
        for _ in range(args.ratio):
            sample = rb.sample().reshape(-1, args.length)
            loss = open_loop(model, sample)
            model_opt.zero_grad()
            loss.backward()
            model_opt.step()
            starts = observed(sample["observation"].reshape(-1, 5)).float()
            cost = imagined(model, learner, starts, horizon=15)
            actor_opt.zero_grad()
            cost.backward()
            actor_opt.step()
            losses.append(float(loss))
        collector.update_policy_weights_({k: v.double() for k, v in
                                          learner.state_dict().items()})
    collector.shutdown()
    print(f"steps per episode: {episode_lengths[0]:.1f} in the first batch, "
          f"{sum(episode_lengths[-5:]) / len(episode_lengths[-5:]):.1f} in the last five; "
          f"world model loss {losses[0] if losses else float('nan'):.2e} -> "
          f"{losses[-1] if losses else float('nan'):.2e}")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.5))
    a.semilogy(losses)
    a.set(xlabel="update", ylabel="open-loop window error", title="world model")
    b.plot(episode_lengths)
    b.set(xlabel="batch collected", ylabel="steps per episode", title="acting policy")
    fig.tight_layout()
    os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
    fig.savefig(args.out, dpi=120)
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
