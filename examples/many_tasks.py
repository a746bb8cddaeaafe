"""Train one dynamics model on several robots at once, from a padded `simloader.Mixture`.

Streams batches of `Mixture(..., pad=True)` over several models (simloader's built-in
cart-pole and humanoid, and Gymnasium's MuJoCo models where `gymnasium` is installed): every
batch holds rows of each drawn task, padded to the widest state and control, with
`batch["task"]` per row and `batch["mask/KEY"]` marking the real columns. One torch MLP,
given the padded state, the padded control and a learned embedding of the task, predicts the
change of state; the loss counts the real columns only. At the end it prints, per task, the
training loss and the one-step error on held-out trajectories. CPU engine by default.

    python examples/many_tasks.py                  # full run
    python examples/many_tasks.py --quick          # seconds, as the test suite runs it
    python examples/many_tasks.py --models cartpole gymnasium/hopper --backend mjx
"""

import argparse
import os
import time

import torch
from torch import nn

import simloader
from simloader import controls

# what the full run mixes, where available (Gymnasium's models need `pip install gymnasium`)
MODELS = ["cartpole", "humanoid", "gymnasium/hopper", "gymnasium/half_cheetah",
          "gymnasium/walker2d"]
QUICK_MODELS = ["cartpole", "humanoid", "gymnasium/hopper"]


def available(names):
    """The names a user's install can load: the built-in ones, Gymnasium's if installed."""
    known = simloader.named_models()
    found = [n for n in names if n in known]
    missing = [n for n in names if n not in known]
    if missing:
        print(f"not available here, left out: {missing} (Gymnasium's models need "
              f"`python3 -m pip install gymnasium`)")
    if len(found) < 2:  # a mixture of one is no mixture: fall back on the built-in models
        found = simloader.builtin_models()
    return found


def member(name, args, nthread, device, seed):
    """One task's stream: the same nstep, record, device and dtype in every member (pad=True
    needs them alike), its own model, controls and seed."""
    return simloader.SimDataset(
        name, backend=args.backend, nbatch=args.nbatch, nstep=args.nstep, seed=seed,
        control=controls.OrnsteinUhlenbeck(std=0.5, tau=0.2),
        initial_state=simloader.initial.Perturbed(qpos_std=0.05, qvel_std=0.05),
        record=("state",), device=device, dtype=torch.float32, nthread=nthread)


def pairs(batch):
    """(s, a, s', state mask, control mask, task), one row per step of each trajectory.

    The state's column 0 is time in every member (mjSTATE_FULLPHYSICS): dropped, so the
    padded columns 1.. are [qpos, qvel] of each row's own model."""
    states = torch.cat([batch["initial_state"][:, None], batch["state"]], dim=1)[..., 1:]
    nrows, nframes = batch["state"].shape[:2]
    s, s_next = states[:, :-1], states[:, 1:]
    a = batch["control"]
    state_mask, control_mask = (
        # "mask/KEY" is there when the members' widths differ; else every column is real
        batch.get("mask/" + key, torch.ones(nrows, batch[key].shape[-1], dtype=torch.bool,
                                            device=a.device))
        for key in ("state", "control"))
    state_mask = state_mask[:, 1:]

    def steps(x):  # (nrows, ...) per trajectory -> (nrows * nframes, ...) per step
        return x[:, None].expand(nrows, nframes, *x.shape[1:]).flatten(0, 1)

    return (s.flatten(0, 1), a.flatten(0, 1), s_next.flatten(0, 1), steps(state_mask),
            steps(control_mask), steps(batch["task"]))


class Dynamics(nn.Module):
    """s' = s + f(normalized s, a, task embedding) * the task's step size, on padded columns;
    normalized per task, so that a cart-pole's and a humanoid's columns weigh alike."""

    def __init__(self, ntask, nstate, ncontrol, width, embed):
        super().__init__()
        self.task = nn.Embedding(ntask, embed)
        self.net = nn.Sequential(nn.Linear(nstate + ncontrol + embed, width), nn.SiLU(),
                                 nn.Linear(width, width), nn.SiLU(), nn.Linear(width, nstate))
        # per task and column; padded columns keep mean 0 and std 1 (their zeros stay zeros)
        self.register_buffer("mean", torch.zeros(ntask, nstate + ncontrol))
        self.register_buffer("std", torch.ones(ntask, nstate + ncontrol))
        self.register_buffer("delta_std", torch.ones(ntask, nstate))

    @torch.no_grad()
    def fit_normalization(self, s, a, s_next, state_mask, control_mask, task):
        x, real = torch.cat([s, a], -1), torch.cat([state_mask, control_mask], -1)
        for t in task.unique():
            rows = task == t
            cols = real[rows][0]  # a task's real columns are the same in every row
            self.mean[t, cols] = x[rows][:, cols].mean(0)
            self.std[t, cols] = x[rows][:, cols].std(0).clamp_min(1e-6)
            self.delta_std[t, cols[:s.shape[-1]]] = \
                (s_next - s)[rows][:, cols[:s.shape[-1]]].std(0).clamp_min(1e-6)

    def forward(self, s, a, task):
        x = (torch.cat([s, a], -1) - self.mean[task]) / self.std[task]
        return s + self.net(torch.cat([x, self.task(task)], -1)) * self.delta_std[task]

    def errors(self, s, a, s_next, state_mask, task):
        """(rows,) mean squared error of the predicted change of state over each row's real
        columns, in units of the task's spread; the padded columns count for nothing."""
        err = ((self(s, a, task) - s_next) / self.delta_std[task]) ** 2
        return (err * state_mask).sum(-1) / state_mask.sum(-1).clamp_min(1)


def rows_of_every_task(mixture, ntask, limit=50):
    """Padded batches of `mixture`, their rows together, until every task has rows (each
    padded batch holds the rows of `ntask` draws, which need not be `ntask` tasks)."""
    keys = ("state", "initial_state", "control", "task", "diverged", "mask/state",
            "mask/control")
    batches, seen = [], set()
    for batch, _ in zip(mixture, range(limit)):
        batches.append({k: batch[k] for k in keys if k in batch})
        seen.update(batch["task"].unique().tolist())
        if len(seen) == ntask:
            break
    out = {k: torch.cat([b[k] for b in batches]) for k in batches[0]}
    return {k: v[~out["diverged"]] for k, v in out.items()}


def per_task(values, task, ntask):
    """Mean of `values` per task (NaN for a task without rows)."""
    sums = torch.zeros(ntask, device=values.device).index_add_(0, task, values)
    counts = torch.zeros(ntask, device=values.device).index_add_(0, task,
                                                                 torch.ones_like(values))
    return sums / counts


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="cpu", choices=("cpu", "mjx", "warp", "auto"))
    parser.add_argument("--models", nargs="+",
                        help=f"models to mix (default: those of {MODELS} available here)")
    parser.add_argument("--weights", nargs="+", type=float,
                        help="one share per model (default: equal)")
    parser.add_argument("--batches", type=int, default=200,
                        help="training batches (each holds rows of every drawn task)")
    parser.add_argument("--nbatch", type=int, default=256, help="trajectories per member batch")
    parser.add_argument("--nstep", type=int, default=50)
    parser.add_argument("--width", type=int, default=256)
    parser.add_argument("--embed", type=int, default=8, help="size of the task embedding")
    args = parser.parse_args()
    if args.quick:
        args.batches, args.nbatch, args.nstep, args.width = 80, 16, 20, 64
    names = available(args.models or (QUICK_MODELS if args.quick else MODELS))

    device = "cuda" if torch.cuda.is_available() and args.backend != "cpu" else "cpu"
    # every running member has its own prefetch thread and CPU threads: share the cores
    nthread = max(1, (os.cpu_count() or 1) // len(names))
    members = {n: member(n, args, nthread, device, seed=i) for i, n in enumerate(names)}
    mixture = simloader.Mixture(members, weights=args.weights, seed=0, pad=True)
    # held out: other seeds, the same models, padded by a mixture of their own; and rows of
    # every task from a third one, to normalize with
    def rows(seed):
        return rows_of_every_task(simloader.Mixture(
            {n: member(n, args, nthread, device, seed=seed + i) for i, n in enumerate(names)},
            seed=seed, pad=True), len(names))

    held_out, fit = rows(100), rows(200)

    nstate = held_out["state"].shape[-1] - 1  # time dropped
    ncontrol = held_out["control"].shape[-1]
    net = Dynamics(len(names), nstate, ncontrol, args.width, args.embed).to(device)
    s, a, s_next, smask, cmask, task = pairs(fit)
    net.fit_normalization(s, a, s_next, smask, cmask, task)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.batches)
    print(f"{len(names)} tasks, padded to {nstate} state and {ncontrol} control columns "
          f"(backend {mixture.datasets[0].config.backend}, {nthread} thread(s) per member):")
    for i, n in enumerate(names):
        m = members[n].model
        print(f"  task {i} {n}: nq {m.nq}, nv {m.nv}, nu {m.nu}, share {mixture.weights[i]:.2f}")

    train_loss = torch.full((len(names),), float("nan"))
    start = time.perf_counter()
    loader = torch.utils.data.DataLoader(mixture, batch_size=None)
    for step, batch in zip(range(args.batches), loader):
        keep = ~batch["diverged"]  # never train on non-physics
        s, a, s_next, smask, cmask, task = pairs({k: v[keep] for k, v in batch.items()})
        for chunk in torch.randperm(len(s), device=s.device).split(4096):
            errors = net.errors(s[chunk], a[chunk], s_next[chunk], smask[chunk], task[chunk])
            loss = errors.mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        sched.step()
        seen = per_task(errors.detach(), task[chunk], len(names)).cpu()
        train_loss = torch.where(seen.isnan(), train_loss, seen)
        if step % max(1, args.batches // 10) == 0:
            print(f"batch {step:4d}: loss {loss.item():.3e}")
    print(f"trained on {args.batches} batches in {time.perf_counter() - start:.1f} s")

    with torch.no_grad():
        s, a, s_next, smask, _, task = pairs(held_out)
        held = per_task(net.errors(s, a, s_next, smask, task), task, len(names)).cpu()
    print("per task: training loss (last batch with its rows), held-out one-step MSE (in "
          "units of the task's spread of state changes)")
    for i, n in enumerate(names):
        print(f"  task {i} {n:24s} train {train_loss[i].item():.3e}  held-out "
              f"{held[i].item():.3e}")


if __name__ == "__main__":
    main()
