"""Train a dynamics (world) model on freshly simulated cart-pole transitions.

Streams `(s_t, a_t, s_t+1)` from simloader's built-in cart-pole under smooth random controls
(Ornstein-Uhlenbeck noise), trains a torch MLP to predict the change of state, and reports
one-step and 50-step open-loop prediction errors on held-out trajectories, with a plot of
predicted against simulated trajectories. MJX on a GPU, the rollout backend otherwise.

    python examples/train_world_model.py            # full run
    python examples/train_world_model.py --quick    # a few seconds, as CI runs it
"""

import argparse
import pathlib
import time

import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader import controls

HORIZON = 50


def transitions(batch, physics):
    """(s, a, s') with s = [qpos, qvel] (time dropped), flattened over trajectories and steps."""
    states = torch.cat([batch["initial_state"][:, None], batch["state"]], dim=1)[..., physics]
    return (states[:, :-1].flatten(0, 1), batch["control"].flatten(0, 1),
            states[:, 1:].flatten(0, 1))


class Dynamics(nn.Module):
    """s_t+1 = s_t + f((s_t, a_t) normalized) * scale: a residual MLP on normalized inputs."""

    def __init__(self, nstate, ncontrol, width):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(nstate + ncontrol, width), nn.SiLU(),
                                 nn.Linear(width, width), nn.SiLU(), nn.Linear(width, nstate))
        self.register_buffer("mean", torch.zeros(nstate + ncontrol))
        self.register_buffer("std", torch.ones(nstate + ncontrol))
        self.register_buffer("delta_std", torch.ones(nstate))

    def fit_normalization(self, s, a, s_next):
        x = torch.cat([s, a], -1)
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-6))
        self.delta_std.copy_((s_next - s).std(0).clamp_min(1e-6))

    def forward(self, s, a):
        x = (torch.cat([s, a], -1) - self.mean) / self.std
        return s + self.net(x) * self.delta_std

    def loss(self, s, a, s_next):
        """Mean squared error of the predicted change of state, in units of its spread."""
        return nn.functional.mse_loss((self(s, a) - s) / self.delta_std,
                                      (s_next - s) / self.delta_std)


@torch.no_grad()
def evaluate(net, held_out, physics):
    """Prints the one-step and HORIZON-step open-loop RMSE on held-out trajectories.

    Returns:
      (truth, prediction, open-loop RMSE per step).
    """
    s, a, s_next = transitions(held_out, physics)
    one_step = ((net(s, a) - s_next) ** 2).mean().sqrt().item()
    truth = held_out["state"][..., physics]
    pred, x = [], held_out["initial_state"][:, physics]
    for t in range(truth.shape[1]):  # open loop: the model feeds on its own predictions
        x = net(x, held_out["control"][:, t])
        pred.append(x)
    pred = torch.stack(pred, 1)
    err = (pred - truth).pow(2).mean(dim=(0, 2)).sqrt()
    scale = truth.std().item()
    print(f"one-step RMSE:            {one_step:.2e}  ({one_step / scale:.2%} of the state's std)")
    print(f"{len(err)}-step open-loop RMSE: {err[-1].item():.2e}  "
          f"({err[-1].item() / scale:.2%} of the state's std)")
    return truth, pred, err


def setup(args, device):
    """The training stream, held-out trajectories and a dynamics model normalized on them.

    Returns:
      (backend, training SimDataset, held-out batch, model, the state's physics columns).
    """
    common = dict(device=device, dtype=torch.float32,
                  control=controls.OrnsteinUhlenbeck(std=0.6, tau=0.2),
                  initial_state=simloader.initial.Perturbed(qpos_std=0.3, qvel_std=0.3))
    # under torchrun, every rank passes the same arguments and streams its own part of seed 0
    train = simloader.SimDataset("cartpole", backend=args.backend, nbatch=args.nbatch,
                                 nstep=args.nstep, num_batches=args.batches, seed=0, **common)
    # held out on the engine that simulates the training stream ("auto" chose it for its size)
    backend = train.config.backend
    held_out = next(iter(simloader.SimDataset("cartpole", backend=backend, nbatch=64,
                                              nstep=HORIZON, seed=1, **common)))
    model = train.model
    physics = slice(1, 1 + model.nq + model.nv)  # drop time, the state's first column
    net = Dynamics(model.nq + model.nv, model.nu, args.width).to(device)
    net.fit_normalization(*transitions(held_out, physics))
    return backend, train, held_out, net, physics


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--batches", type=int, default=300)
    parser.add_argument("--nbatch", type=int, default=1024)
    parser.add_argument("--nstep", type=int, default=100)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--out", default="outputs/world_model.png",
                        help="where to save the plot (outputs/ is git-ignored; the docs' one "
                             "was made with --out docs/_static/world_model.png)")
    args = parser.parse_args()
    if args.quick:
        args.batches, args.nbatch, args.nstep, args.width = 15, 64, 60, 64

    device = "cuda" if torch.cuda.is_available() else "cpu"
    backend, train, held_out, net, physics = setup(args, device)
    model = train.model
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.batches)
    print(f"backend {backend} on {device}: {args.batches} batches of {args.nbatch} x {args.nstep}")
    start = time.perf_counter()
    progress = tqdm(torch.utils.data.DataLoader(train, batch_size=None), total=args.batches)
    for batch in progress:
        keep = ~batch["diverged"]  # never train on non-physics
        s, a, s_next = transitions({k: v[keep] for k, v in batch.items()}, physics)
        for chunk in torch.randperm(len(s), device=device).split(8192):
            loss = net.loss(s[chunk], a[chunk], s_next[chunk])
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        progress.set_postfix(loss=f"{loss.item():.2e}")
    print(f"trained in {time.perf_counter() - start:.1f} s")

    truth, pred, err = evaluate(net, held_out, physics)

    plot_open_loop(truth, pred, {"cart position": 0, "pole angle": 1}, model.opt.timestep,
                   f"cart-pole world model, {HORIZON}-step open-loop RMSE "
                   f"{err[-1].item():.2e} ({backend})", args.out)


def plot_open_loop(truth, pred, columns, dt, title, out):
    """Predicted (open loop) against simulated trajectories: a row per named state column
    (`columns`: {name: column}), a column per trajectory, saved to `out`."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    t = torch.arange(1, truth.shape[1] + 1).numpy() * dt
    fig, axes = plt.subplots(len(columns), 3, figsize=(12, 3 * len(columns)), sharex=True)
    for j in range(3):
        for i, (name, column) in enumerate(columns.items()):
            ax = axes[i, j]
            ax.plot(t, truth[j, :, column].cpu(), "k-", label="simulated")
            ax.plot(t, pred[j, :, column].cpu(), "r--", label="predicted (open loop)")
            ax.set_title(f"trajectory {j}: {name}")
            ax.set_xlabel("time [s]")
    axes[0, 0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    out = pathlib.Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"plot saved to {out}")


if __name__ == "__main__":
    main()
