"""A humanoid under random actuator controls, dragged by a Cartesian force on its head.

`control_spec = CTRL | XFRC_APPLIED`: the control row holds the actuators, then 6 values
(force, torque) per body. With simloader the force is addressed by body name: no offset
arithmetic (6 per body, not 3).

    python examples/dragging_humanoid.py --model path/to/humanoid.xml [--quick]
"""

import argparse
import pathlib

import mujoco
import torch

import simloader
from simloader import controls

S = mujoco.mjtState
DEFAULT_MODELS = [pathlib.Path(".models/dm_control/humanoid.xml"),
                  pathlib.Path(__file__).resolve().parents[2] / "shared/models/dm_control/humanoid.xml"]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", help="humanoid MJCF (default: the dm_control humanoid)")
    parser.add_argument("--backend", default="auto", choices=("auto", "rollout", "mjx"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    path = args.model or next((p for p in DEFAULT_MODELS if p.is_file()), None)
    if path is None:
        raise SystemExit("no humanoid model found: pass --model path/to/humanoid.xml")
    nbatch, nstep = (4, 20) if args.quick else (512, 300)

    pull = 150.0  # newtons along +x on the head
    ds = simloader.SimDataset(
        str(path), backend=args.backend, nbatch=nbatch, nstep=nstep, num_batches=1,
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
