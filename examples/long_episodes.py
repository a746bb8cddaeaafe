"""Trajectories longer than one batch: `continue_episodes=True`.

Each batch continues every trajectory where the previous batch ended (solver warmstart
included), so consecutive batches concatenate to exactly one long rollout. This script streams
a 2,000-step episode in chunks of 200 steps and checks it against one `mujoco.rollout` call.

    python examples/long_episodes.py [--quick]
"""

import argparse

import mujoco
import numpy as np
import torch
from mujoco import rollout

import simloader
from simloader import controls


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    nbatch, chunk, nchunk = (8, 50, 4) if args.quick else (256, 200, 10)

    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=nbatch, nstep=chunk,
                              control=controls.OrnsteinUhlenbeck(std=0.5, tau=0.3),
                              initial_state=simloader.initial.Perturbed(),
                              continue_episodes=True, num_batches=nchunk, seed=0)
    batches = list(torch.utils.data.DataLoader(ds, batch_size=None))
    episode = torch.cat([b["state"] for b in batches], dim=1)  # (nbatch, nchunk * chunk, nstate)
    print(f"{nbatch} episodes of {episode.shape[1]} steps streamed in {nchunk} chunks of {chunk}")

    # the same episodes as one long rollout
    model = ds.model
    control = torch.cat([b["control"] for b in batches], dim=1).numpy()
    state, _ = rollout.rollout(model, [mujoco.MjData(model) for _ in range(2)],
                               batches[0]["initial_state"].numpy(), control)
    identical = np.array_equal(state, episode.numpy())
    print(f"equal to one mujoco.rollout of {state.shape[1]} steps, bit for bit: {identical}")
    print(f"final simulated time: {episode[0, -1, 0].item():.2f} s")
    if not identical:
        raise SystemExit("continuation differs from one long rollout")


if __name__ == "__main__":
    main()
