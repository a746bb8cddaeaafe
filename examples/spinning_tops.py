"""Spinning tops from a keyframe at many spin rates, their gyro sensor plotted.

Every trajectory starts from the `tilted` keyframe with its own spin rate about the top's axis
(an `initial_state` array, one row per trajectory); fast tops stay up and precess, slow ones
fall. The plot shows the gyro's readings over time for a few rates.

    python examples/spinning_tops.py [--quick] [--out outputs/spinning_tops.png]
"""

import argparse
import pathlib

import numpy as np
import torch

import simloader

TOP_XML = """
<mujoco model="top">
  <option timestep="0.002" integrator="implicitfast"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 .1"/>
    <body name="top" pos="0 0 0.1">
      <freejoint name="top"/>
      <geom name="disk" type="cylinder" size="0.1 0.01" pos="0 0 0.05" mass="0.5"/>
      <geom name="stem" type="capsule" fromto="0 0 -0.05 0 0 0.12" size="0.008" mass="0.02"/>
      <site name="imu" pos="0 0 0.05"/>
    </body>
  </worldbody>
  <sensor>
    <gyro name="gyro" site="imu"/>
  </sensor>
  <keyframe>
    <key name="tilted" qpos="0 0 0.06 0.9962 0.0872 0 0"/>
  </keyframe>
</mujoco>
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default="outputs/spinning_tops.png",
                        help="where to save the plot (outputs/ is git-ignored)")
    args = parser.parse_args()
    nbatch, nstep = (8, 200) if args.quick else (64, 2000)

    model = simloader.load_model(TOP_XML)
    base = simloader.initial.keyframe_state(model, "tilted")
    spins = np.linspace(5.0, 150.0, nbatch)  # rad/s about the top's own axis
    x0 = np.tile(base, (nbatch, 1))
    qvel = 1 + model.nq  # state = [time, qpos, qvel, ...]; the free joint's angular velocity
    x0[:, qvel + 5] = spins  # is in the body frame: index 5 is the spin about the top's axis
    ds = simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep,
                              initial_state=x0, num_batches=1)
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=None)))
    gyro = batch["sensordata"].numpy()  # (nbatch, nstep, 3), the top's frame
    height = batch["state"][..., 1 + 2].numpy()  # z of the top's centre
    upright = height[:, -1] > 0.05
    print(f"{nbatch} tops, spin rates {spins[0]:.0f}..{spins[-1]:.0f} rad/s, "
          f"{nstep * model.opt.timestep:.1f} s: {upright.sum()} still up; slowest up: "
          f"{spins[upright].min() if upright.any() else float('nan'):.0f} rad/s")

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    t = np.arange(1, nstep + 1) * model.opt.timestep
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for i in np.linspace(0, nbatch - 1, 4).astype(int):
        axes[0].plot(t, gyro[i, :, 2], label=f"{spins[i]:.0f} rad/s")
        axes[1].plot(t, np.hypot(gyro[i, :, 0], gyro[i, :, 1]), label=f"{spins[i]:.0f} rad/s")
    axes[0].set_title("gyro: spin about the top's axis [rad/s]")
    axes[1].set_title("gyro: wobble (transverse rate) [rad/s]")
    for ax in axes:
        ax.set_xlabel("time [s]")
        ax.legend()
    fig.tight_layout()
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    print(f"plot saved to {out}")


if __name__ == "__main__":
    main()
