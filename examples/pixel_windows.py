"""A recurrent pixel world model trained on windows of a store, DreamerV3's way.

The store keeps states only (episodes of the cart-pole that end when the pole falls past
0.2 rad); pixels are rendered on read for exactly the frames of each window
(`StoredDataset(path, cameras=...)`). Windows cross episode ends (`ends="cross"`), the fresh
frame marked `first`, where the model resets its recurrent state; the action is the one taken
after each frame (`actions="next"`, zeros after an episode's last frame). The model encodes
each frame, steps a GRU with the action, and predicts the next frame's pixels; the loss skips
the targets that are fresh starts (no action led there). The plot shows the training loss
and, for one held-out window, the frames next to the model's one-step predictions.

    python examples/pixel_windows.py                  # about 5 minutes on a 2-core CPU
    python examples/pixel_windows.py --quick          # seconds, as CI runs it

On a CPU without a GPU, MuJoCo's renderer runs on software OpenGL at about 27 ms a frame even
at 32 x 32 (its shadows and multisampling), which sets the pace here: a GPU's OpenGL, or
`StoredDataset(..., backend="warp", device="cuda")`, renders far faster.
"""

import argparse
import os
import tempfile
import time

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

import simloader
from simloader.terminate import Outside


class PixelModel(nn.Module):
    """Frame t and action t -> frame t + 1, through a GRU state reset at `first` frames."""

    def __init__(self, size: int, nu: int, width: int):
        super().__init__()
        self.size = size
        self.encode = nn.Sequential(
            nn.Conv2d(3, 16, 4, 2, 1), nn.ReLU(), nn.Conv2d(16, 32, 4, 2, 1), nn.ReLU(),
            nn.Flatten(), nn.Linear(32 * (size // 4) ** 2, width))
        self.cell = nn.GRUCell(width + nu, width)
        self.decode = nn.Sequential(nn.Linear(width, 32 * (size // 4) ** 2), nn.ReLU(),
                                    nn.Unflatten(1, (32, size // 4, size // 4)),
                                    nn.ConvTranspose2d(32, 16, 4, 2, 1), nn.ReLU(),
                                    nn.ConvTranspose2d(16, 3, 4, 2, 1))

    def forward(self, pixels: torch.Tensor, action: torch.Tensor,
                first: torch.Tensor) -> torch.Tensor:
        """pixels (B, L, H, W, 3) uint8, action (B, L, nu), first (B, L) -> predicted frames
        t + 1 for t < L - 1, (B, L - 1, 3, H, W) in [0, 1]."""
        b, length = pixels.shape[:2]
        images = pixels.permute(0, 1, 4, 2, 3).float() / 255
        embedded = self.encode(images.reshape(b * length, *images.shape[2:])).reshape(
            b, length, -1)
        h = torch.zeros(b, self.cell.hidden_size, device=pixels.device)
        out = []
        for t in range(length - 1):
            h = h * (~first[:, t])[:, None]  # a fresh episode: forget the last one
            h = self.cell(torch.cat([embedded[:, t], action[:, t]], -1), h)
            out.append(torch.sigmoid(self.decode(h)))
        return torch.stack(out, 1)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, seconds")
    parser.add_argument("--length", type=int, default=16, help="frames per window")
    parser.add_argument("--batch-size", type=int, default=8, help="windows per step")
    parser.add_argument("--steps", type=int, default=80, help="training steps")
    parser.add_argument("--size", type=int, default=32, help="camera height and width")
    parser.add_argument("--out", default="outputs/pixel_windows.png",
                        help="where to save the plot (outputs/ is git-ignored)")
    args = parser.parse_args()
    batches, nbatch, nstep = 4, 16, 100
    if args.quick:
        batches, nbatch, nstep, args.steps, args.batch_size = 2, 4, 30, 6, 4
        args.length, args.size = 8, 16
    scratch = tempfile.TemporaryDirectory()
    path = os.path.join(scratch.name, "cartpole-episodes.zarr")

    # 1. a store of states: episodes that end when the pole falls
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=nbatch, nstep=nstep, seed=0,
                              control=simloader.controls.Uniform(), record=("state",),
                              terminate=Outside("hinge", -0.2, 0.2))
    simloader.write(ds, path, batches=batches, progress=False)

    # 2. windows with their pixels rendered on read, DreamerV3's conventions
    camera = simloader.Camera("front", height=args.size, width=args.size)
    stored = simloader.StoredDataset(path, cameras=camera)
    windows = stored.windows(args.length, ends="cross", actions="next")
    key = "camera/front/rgb"
    print(f"{len(windows):,} windows of {args.length} frames from {len(stored)} trajectories; "
          f"{int(stored.episodes().lengths().size)} episodes")
    held_out = windows.gather([len(windows) // 2])

    net = PixelModel(args.size, ds.model.nu, 128)
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    losses = []
    start = time.perf_counter()
    loader = windows.loader(args.batch_size, seed=0, drop_last=True)
    progress = tqdm(total=args.steps, desc="training", disable=args.quick)
    while len(losses) < args.steps:
        for batch in loader:
            predicted = net(batch[key], batch["control"].float(), batch["first"])
            target = batch[key][:, 1:].permute(0, 1, 4, 2, 3).float() / 255
            learnable = ~batch["first"][:, 1:]  # a fresh start follows no action
            error = ((predicted - target) ** 2).mean((2, 3, 4))
            loss = (error * learnable).sum() / learnable.sum().clamp(min=1)
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
            progress.update(1)
            if len(losses) >= args.steps:
                break
    progress.close()
    seconds = time.perf_counter() - start
    print(f"{len(losses)} steps in {seconds:.1f} s; loss {losses[0]:.4f} -> {losses[-1]:.4f}")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    with torch.no_grad():
        guess = net(held_out[key], held_out["control"].float(), held_out["first"])[0]
    shown = min(6, args.length - 1)
    fig = plt.figure(figsize=(2 + 1.6 * shown, 5.2))
    grid = fig.add_gridspec(3, shown, height_ratios=[1.4, 1, 1])
    curve = fig.add_subplot(grid[0, :])
    curve.plot(losses)
    curve.set_yscale("log")
    curve.set_xlabel("training step")
    curve.set_ylabel("next-frame MSE")
    curve.set_title(f"a GRU pixel model on {args.length}-frame windows rendered on read")
    for t in range(shown):
        for row, image, label in ((1, held_out[key][0, t + 1].numpy(), "frame"),
                                  (2, guess[t].permute(1, 2, 0).numpy(), "predicted")):
            ax = fig.add_subplot(grid[row, t])
            ax.imshow(image)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{label} t+{t + 1}" + (" (first)" if row == 1 and
                                                 held_out["first"][0, t + 1] else ""),
                         fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"plot: {args.out}")
    scratch.cleanup()
    assert np.isfinite(losses).all()


if __name__ == "__main__":
    main()
