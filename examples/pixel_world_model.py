"""Train a pixel world model: predict the cart-pole's next camera frame from the frame and the
action.

Streams freshly rendered 32x32 RGB frames of simloader's built-in cart-pole (camera "front")
under smooth random pushes, and trains a small convolutional encoder-decoder: the encoder sees
the last two frames (one frame shows no velocity), the action enters the bottleneck, the
decoder predicts the next frame. Held-out trajectories are then rolled out open loop from two
true frames, the model feeding on its own predictions, and a picture of predicted against true
frames is saved. MJX renders on MuJoCo Warp on a GPU; the rollout backend renders with
`mujoco.Renderer` on CPU threads.

    python examples/pixel_world_model.py            # full run
    python examples/pixel_world_model.py --quick    # a few seconds, as CI runs it
"""

import argparse
import pathlib
import time

import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader import controls

KEY = "camera/front/rgb"
CONTEXT = 2  # frames the model sees


def frames(batch):
    """(nbatch, nframes, 3, H, W) float in [0, 1] (frame j: after step 2(j + 1))."""
    return batch[KEY].permute(0, 1, 4, 2, 3).float() / 255


class FrameModel(nn.Module):
    """x_t+1 = decode(encode(x_t-1, x_t), a_t): a convolutional encoder-decoder."""

    def __init__(self, ncontrol, width):
        super().__init__()
        self.encode = nn.Sequential(
            nn.Conv2d(3 * CONTEXT, width, 4, 2, 1), nn.SiLU(),           # 16x16
            nn.Conv2d(width, 2 * width, 4, 2, 1), nn.SiLU(),             # 8x8
            nn.Conv2d(2 * width, 2 * width, 3, 1, 1), nn.SiLU())
        self.action = nn.Linear(ncontrol, 2 * width)
        self.decode = nn.Sequential(
            nn.Conv2d(2 * width, 2 * width, 3, 1, 1), nn.SiLU(),
            nn.ConvTranspose2d(2 * width, width, 4, 2, 1), nn.SiLU(),    # 16x16
            nn.ConvTranspose2d(width, 3, 4, 2, 1))                       # 32x32

    def forward(self, context, action):
        """context: (n, CONTEXT, 3, H, W); action: (n, ncontrol) -> next frame (n, 3, H, W)."""
        z = self.encode(context.flatten(1, 2))
        z = z + self.action(action)[:, :, None, None]
        # residual on the last frame: most pixels do not change
        return (context[:, -1] + self.decode(z)).clamp(0, 1)


def windows(video, control):
    """Training tuples from (n, T, 3, H, W) frames and their (n, T, ncontrol) actions (action
    j: what acted on the way to frame j): frames t-1 and t, action t + 1, frame t + 1."""
    n, t = video.shape[:2]
    ctx = torch.stack([video[:, i:t - CONTEXT + 1 + i] for i in range(CONTEXT)], 2)
    return (ctx[:, :-1].flatten(0, 1), control[:, CONTEXT:].flatten(0, 1),
            video[:, CONTEXT:].flatten(0, 1))


@torch.no_grad()
def rollout(net, video, control, horizon):
    """Open-loop predictions of `horizon` frames after the first CONTEXT true ones."""
    ctx, out = video[:, :CONTEXT], []
    for t in range(horizon):
        nxt = net(ctx, control[:, CONTEXT + t])
        out.append(nxt)
        ctx = torch.cat([ctx[:, 1:], nxt[:, None]], 1)
    return torch.stack(out, 1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--batches", type=int, default=400)
    parser.add_argument("--nbatch", type=int, default=256)
    parser.add_argument("--nstep", type=int, default=40)
    parser.add_argument("--width", type=int, default=32)
    parser.add_argument("--out", default="outputs/pixel_world_model.png",
                        help="where to save the picture (outputs/ is git-ignored; the docs' one "
                             "was made with --out docs/_static/pixel_world_model.png)")
    args = parser.parse_args()
    if args.quick:
        # CPU rendering (Mesa) is the cost: 2 batches of 4 x 6 frames, 2 held-out trajectories
        args.batches, args.nbatch, args.nstep, args.width = 2, 4, 12, 8

    device = "cuda" if torch.cuda.is_available() else "cpu"
    # a frame every other step (0.02 s): the camera sees motion, the renderer half the work
    common = dict(device=device, record_every=2,
                  record=(simloader.Camera("front", height=32, width=32),),
                  control=controls.OrnsteinUhlenbeck(std=0.8, tau=0.3),
                  initial_state=simloader.initial.Perturbed(qpos_std=0.5, qvel_std=0.5))
    train = simloader.SimDataset("cartpole", backend=args.backend, nbatch=args.nbatch,
                                 nstep=args.nstep, num_batches=args.batches, seed=0, **common)
    # held out on the engine that renders the training stream ("auto" chose it for its size)
    backend = train.config.backend
    held_out = next(iter(simloader.SimDataset("cartpole", backend=backend,
                                              nbatch=2 if args.quick else 8,
                                              nstep=args.nstep, seed=1, **common)))
    nu = train.model.nu
    net = FrameModel(nu, args.width).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.batches)
    print(f"backend {backend} on {device}: {args.batches} batches of {args.nbatch} trajectories "
          f"x {args.nstep // 2} frames of 32x32 RGB")
    if backend == "cpu" and not args.quick:
        # OpenGL on a CPU is Mesa's software rasterizer: about 36 frames/s at 32x32 on a
        # 2-core machine (as fast as a plain mujoco.Renderer there), so the default run takes
        # about 14 hours on such a machine
        print(f"note: rendering on the CPU: {args.batches * args.nbatch * args.nstep // 2:,} "
              f"frames, about 36 frames/s per 2 cores with Mesa; --quick runs in seconds, a "
              f"GPU (backend='warp') renders millions per second")

    def actions(batch):
        # the action of frame j: the mean control of its two steps
        u = batch["control"].float()
        return u.reshape(u.shape[0], -1, 2, u.shape[-1]).mean(2)

    start = time.perf_counter()
    progress = tqdm(torch.utils.data.DataLoader(train, batch_size=None), total=args.batches)
    for batch in progress:
        keep = ~batch["diverged"]
        ctx, a, target = windows(frames(batch)[keep], actions(batch)[keep])
        loss = nn.functional.mse_loss(net(ctx, a), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        progress.set_postfix(loss=f"{loss.item():.2e}")
    print(f"trained in {time.perf_counter() - start:.1f} s")

    video, u = frames(held_out), actions(held_out)
    horizon = video.shape[1] - CONTEXT
    pred = rollout(net, video, u, horizon)
    truth = video[:, CONTEXT:]
    err = (pred - truth).pow(2).mean(dim=(0, 2, 3, 4)).sqrt()
    still = (video[:, CONTEXT - 1:CONTEXT] - truth).pow(2).mean(dim=(0, 2, 3, 4)).sqrt()
    print(f"one-frame RMSE {err[0]:.4f} (a model that repeats the last frame: {still[0]:.4f}); "
          f"{horizon}-frame open loop {err[-1]:.4f} ({still[-1]:.4f})")

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no picture")
        return
    shown = min(horizon, 8)
    cols = [round(i * (horizon - 1) / max(shown - 1, 1)) for i in range(shown)]
    fig, axes = plt.subplots(4, shown, figsize=(1.6 * shown, 7), squeeze=False)
    for row, (traj, name) in enumerate([(0, "true"), (0, "predicted"), (1, "true"),
                                        (1, "predicted")]):
        clip = truth if name == "true" else pred
        for k, t in enumerate(cols):
            ax = axes[row, k]
            ax.imshow(clip[traj, t].permute(1, 2, 0).cpu().numpy(), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"+{t + 1} frames", fontsize=8)
            if k == 0:
                ax.set_ylabel(f"traj {traj}\n{name}", fontsize=8)
    fig.suptitle(f"cart-pole pixel world model, open loop from 2 true frames "
                 f"(RMSE {err[-1]:.3f} at +{horizon}; {backend})", fontsize=9)
    fig.tight_layout()
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"picture saved to {out}")


if __name__ == "__main__":
    main()
