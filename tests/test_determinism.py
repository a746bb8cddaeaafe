"""Determinism (reliability check 5): the same seed gives bit-identical batches across fresh
processes on the CPU backend, with random controls, random initial states and randomized model
parameters. (Within one process, and across DataLoader workers and ranks, see test_dataset.py;
MJX on the GPU: benchmarks/experiments/determinism.py.)"""

import hashlib
import json
import pathlib

import mujoco
import torch

import simloader
from simloader import controls
from simloader import randomize as dr

NUM_BATCHES = 4
# a fresh interpreter prints the digests of the stream of seed argv[1]
SCRIPT = f"""
import json, sys
sys.path.insert(0, {str(pathlib.Path(__file__).parent)!r})
from test_determinism import stream_digests
print(json.dumps(stream_digests(int(sys.argv[1]))))
"""


def digests(batch, prefix=""):
    """{key: sha256 of the tensor's bytes, with its dtype and shape}, nested dicts flattened."""
    out = {}
    for key, value in sorted(batch.items()):
        if isinstance(value, dict):
            out.update(digests(value, f"{prefix}{key}/"))
        else:
            data = hashlib.sha256(value.contiguous().numpy().tobytes()).hexdigest()
            out[prefix + key] = f"{data} {value.dtype} {tuple(value.shape)}"
    return out


def stream_digests(seed):
    """The digests of every tensor of every batch of a stream with all randomness in use."""
    S = mujoco.mjtState
    ds = simloader.SimDataset(
        "cartpole", backend="cpu", nbatch=16, nstep=25, num_batches=NUM_BATCHES, seed=seed,
        nthread=2, control_spec=S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED,
        control={"ctrl": controls.OrnsteinUhlenbeck(),
                 "xfrc_applied": controls.Normal(std=0.5, on="pole")},
        initial_state=simloader.initial.Perturbed(qpos_std=0.2, qvel_std=0.2),
        randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole"),
                   dr.add("dof_damping", dr.LogUniform(1e-3, 1.0), on="hinge")])
    return [digests(batch) for batch in ds]


def test_same_seed_gives_identical_batches_in_fresh_processes(fresh_python):
    # two processes at once, with different str hash seeds (set and dict orders of strings)
    first, second = (json.loads(out) for out in fresh_python(
        SCRIPT, [([3], {"PYTHONHASHSEED": "1"}), ([3], {"PYTHONHASHSEED": "2"})]))
    assert len(first) == NUM_BATCHES
    assert set(first[0]) == {"state", "sensordata", "control", "initial_state", "diverged",
                             "params/body_mass[pole]", "params/dof_damping[hinge]",
                             "stream", "episode", "initial_first"}
    assert first == second
    # not identical for want of randomness: every batch and every seed draws anew
    for key in ("state", "control", "initial_state", "params/body_mass[pole]"):
        assert len({batch[key] for batch in first}) == NUM_BATCHES, key
    other = stream_digests(4)
    assert all(a[key] != b[key] for a, b in zip(first, other) for key in a
               if key not in ("diverged", *simloader.streams.KEYS))  # no draws: not seeded


def test_digests_see_every_bit():
    batch = {"state": torch.zeros(2, 3, dtype=torch.float64)}
    flipped = batch["state"].clone()
    flipped.view(torch.int64)[1, 2] ^= 1  # the last bit of the last value
    assert digests(batch) != digests({"state": flipped})
    assert digests(batch) != digests({"state": batch["state"].float()})
