"""A humanoid under random actuator controls, dragged by a Cartesian force on its head.

`control_spec = CTRL | XFRC_APPLIED`: the control row holds the actuators, then 6 values
(force, torque) per body. With simloader the force is addressed by body name: no offset
arithmetic (6 per body, not 3).

    python examples/dragging_humanoid.py [--model path/to/humanoid.xml] [--quick]
"""

import argparse

import mujoco
import torch

import simloader
from simloader import controls

S = mujoco.mjtState


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="humanoid",
                        help="a humanoid MJCF with a body named 'head' (default: the built-in "
                             "DeepMind Control Suite humanoid)")
    parser.add_argument("--backend", default="auto", choices=("auto", "cpu", "mjx", "warp"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    nbatch, nstep = (4, 20) if args.quick else (512, 300)

    pull = 150.0  # newtons along +x on the head
    ds = simloader.SimDataset(
        args.model, backend=args.backend, nbatch=nbatch, nstep=nstep, num_batches=1,
        control_spec=S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED,
        control={"ctrl": controls.Uniform(),
                 "xfrc_applied": controls.Constant([pull, 0, 0, 0, 0, 0], on="head")})
    print(ds.describe().split("sensordata")[0])
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=None)))
    model = ds.model
    qpos = batch["state"][..., 1:1 + model.nq]
    drift = (qpos[:, -1, 0] - batch["initial_state"][:, 1]).mean().item()
    print(f"{nbatch} humanoids, {nstep} steps: the root moved {drift:+.2f} m along x on average "
          f"(pulled by {pull:.0f} N on the head); diverged: {int(batch['diverged'].sum())}")
    if not drift > 0:
        raise SystemExit("the pull on the head did not move the humanoids along +x")


if __name__ == "__main__":
    main()
