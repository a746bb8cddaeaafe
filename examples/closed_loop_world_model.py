"""On-policy world-model data: a feedback controller picks every action, a dynamics model
learns from what it collects.

The policy is a scripted torch module, a linear state-feedback law on the cart-pole's qpos and
qvel that balances the pole, passed as `policy=`. Exploration noise around it comes from
`policy_noise=`. The data is the controller's own: states near upright, which open-loop noise
seldom visits. A dynamics model (an MLP on (s_t, a_t) -> s_t+1) trains on every batch. The
policy returns what it saw as an extra (`policy/state`), so the (s_t, a_t, s_t+1) tuples need
no index arithmetic. The plot shows the fraction of steps each batch kept the pole balanced,
the model's one-step error over the batches, and a trajectory of the last batch
predicted open loop by the model.

    python examples/closed_loop_world_model.py            # full run
    python examples/closed_loop_world_model.py --quick    # a few seconds, as CI runs it
"""

import argparse
import pathlib
import time

import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader import controls

IMAGINED = 30  # steps of the rollouts imagined through the learned model


class Feedback(nn.Module):
    """u = gains . (x, theta, x_dot, theta_dot)."""

    def __init__(self):
        super().__init__()
        # found by a coarse search over signs and magnitudes: balances most perturbed starts
        self.register_buffer("gains", torch.tensor([1.0, 20.0, 1.0, 4.0]))

    def forward(self, obs):
        state = torch.cat([obs["qpos"], obs["qvel"]], -1)
        u = (state * self.gains).sum(-1, keepdim=True)
        return u, {"state": state}  # what the policy saw: s_t of every step, as extras


class Dynamics(nn.Module):
    """s_t+1 = s_t + f(s_t, a_t)."""

    def __init__(self, width):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(5, width), nn.SiLU(), nn.Linear(width, width),
                                 nn.SiLU(), nn.Linear(width, 4))

    def forward(self, s, a):
        return s + 0.05 * self.net(torch.cat([s, a], -1))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--batches", type=int, default=150)
    parser.add_argument("--nbatch", type=int, default=256)
    parser.add_argument("--nstep", type=int, default=200)
    parser.add_argument("--out", default="outputs/closed_loop_world_model.png",
                        help="where to save the plot (outputs/ is git-ignored; the docs' one "
                             "was made with --out docs/_static/closed_loop_world_model.png)")
    args = parser.parse_args()
    if args.quick:
        args.batches, args.nbatch, args.nstep = 8, 32, 60

    device = "cuda" if torch.cuda.is_available() else "cpu"
    policy = Feedback().to(device)
    model = Dynamics(64).to(device)
    ds = simloader.SimDataset(
        "cartpole", backend=args.backend, nbatch=args.nbatch, nstep=args.nstep, device=device,
        dtype=torch.float32, record=("qpos", "qvel"), policy=policy,
        policy_noise=controls.Normal(std=0.2), num_batches=args.batches, prefetch=1,
        initial_state=simloader.initial.Perturbed(qpos_std=0.2, qvel_std=0.5))
    model_opt = torch.optim.Adam(model.parameters(), lr=2e-3)
    history = {"balanced": [], "model_error": []}
    backend = ds.config.backend
    print(f"backend {backend} on {device}: {args.batches} on-policy batches of "
          f"{args.nbatch} x {args.nstep}")
    start = time.perf_counter()
    for batch in tqdm(torch.utils.data.DataLoader(ds, batch_size=None), total=args.batches):
        keep = ~batch["diverged"]
        s = batch["policy/state"][keep]                              # s_t, what the policy saw
        s_next = torch.cat([batch["qpos"], batch["qvel"]], -1)[keep]  # s_t+1
        a = batch["control"][keep]
        # how long the pole stayed within 0.3 rad
        up = (s_next[..., 1].abs() < 0.3).float().cumprod(1).sum(1)
        history["balanced"].append(up.mean().item() / args.nstep)
        # the world model learns from the on-policy transitions
        for chunk in torch.randperm(s.shape[0] * s.shape[1], device=device).split(4096):
            pred = model(s.flatten(0, 1)[chunk], a.flatten(0, 1)[chunk])
            loss = nn.functional.mse_loss(pred, s_next.flatten(0, 1)[chunk])
            model_opt.zero_grad()
            loss.backward()
            model_opt.step()
        history["model_error"].append(loss.sqrt().item())
        last = batch
    print(f"collected and trained in {time.perf_counter() - start:.1f} s; the controller "
          f"balanced {sum(history['balanced']) / len(history['balanced']):.0%} of the steps; "
          f"one-step RMSE {history['model_error'][0]:.2e} at first, "
          f"{history['model_error'][-1]:.2e} at the end")
    # a trajectory of the last batch predicted open loop from its start, under its controls
    with torch.no_grad():
        truth = torch.cat([last["qpos"], last["qvel"]], -1)[0]
        x, pred = last["policy/state"][0, 0], []
        for t in range(truth.shape[0]):
            x = model(x, last["control"][0, t])
            pred.append(x)
        pred = torch.stack(pred)

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    fig, ax = plt.subplots(1, 3, figsize=(14, 3.5))
    ax[0].plot(history["balanced"])
    ax[0].set(xlabel="batch", ylabel="fraction of steps balanced", ylim=(0, 1.05),
              title="scripted controller + noise")
    ax[1].semilogy(history["model_error"])
    ax[1].set(xlabel="batch", ylabel="one-step RMSE", title="world model on on-policy data")
    t = torch.arange(1, truth.shape[0] + 1).numpy() * 0.01
    ax[2].plot(t, truth[:, 1].cpu(), "k-", label="simulated")
    ax[2].plot(t, pred[:, 1].detach().cpu(), "r--", label="model, open loop")
    ax[2].set(xlabel="time [s]", ylabel="pole angle [rad]",
              title="a trajectory of the last batch")
    ax[2].legend()
    fig.suptitle(f"cart-pole, closed loop through simloader ({backend})")
    fig.tight_layout()
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"plot saved to {out}")


if __name__ == "__main__":
    main()
