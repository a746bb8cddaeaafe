"""Fault isolation at the issue's size (reliability check 4), on both backends: a NaN or an
absurd force injected into one trajectory of 1,024 flags exactly that trajectory as diverged,
counts it in `ds.stats`, leaves every other trajectory bit-identical to a run without the fault,
and, with `continue_episodes`, restarts it from its initial state in the next batch (where the
same fault strikes again and must be flagged again). MJX runs on CPU JAX here, with few steps.
"""

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

import simloader
from conftest import FAR_SITE_X0, FAR_SITE_XML, assert_far_site_restarts

S = mujoco.mjtState
SPEC = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED)
NBATCH, NSTEP, NUM_BATCHES = 1024, 5, 2
FAULTY, FAULT_STEP = 613, 2  # the trajectory and the step that get the fault
HINGE = 2  # the control column of the pole's qfrc_applied (after ctrl and the cart's)
FAULTS = {"nan": np.nan, "absurd force": 1e30}
KEYS = ("state", "sensordata", "control", "initial_state", "diverged")


@pytest.fixture(scope="module")
def cartpole():
    return simloader.load_model("cartpole")


def stream(model, backend, control, cache_dir):
    """The batches of a continuing cart-pole stream with the given (fixed) controls, from
    perturbed initial states that differ per trajectory, and its dataset."""
    if backend == "mjx":
        pytest.importorskip("mujoco.mjx")
    x0 = simloader.initial.Perturbed(qpos_std=0.2, qvel_std=0.2).sample(
        model, np.random.default_rng(1), NBATCH)
    options = {"compilation_cache": cache_dir} if backend == "mjx" else {"nthread": 2}
    ds = simloader.SimDataset(model, backend=backend, nbatch=NBATCH, nstep=NSTEP,
                              control=control, control_spec=SPEC, initial_state=x0,
                              continue_episodes=True, num_batches=NUM_BATCHES, **options)
    return ds, x0, list(ds)


def controls(model):
    """A random push on the cart and random joint forces, for every trajectory."""
    rng = np.random.default_rng(0)
    u = np.empty((NBATCH, NSTEP, mujoco.mj_stateSize(model, SPEC)))
    u[..., 0] = rng.uniform(-1, 1, (NBATCH, NSTEP))
    u[..., 1:] = rng.normal(scale=0.5, size=(NBATCH, NSTEP, model.nv))
    return u


@pytest.fixture(scope="module", params=["cpu", "mjx"])
def clean(request, cartpole, cache_dir):
    ds, _, batches = stream(cartpole, request.param, controls(cartpole), cache_dir)
    assert ds.stats["diverged"] == 0 and not any(b["diverged"].any() for b in batches)
    return request.param, batches


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_fault_in_one_of_1024_trajectories_is_isolated(cartpole, cache_dir, clean, fault):
    backend, reference = clean
    u = controls(cartpole)
    u[FAULTY, FAULT_STEP, HINGE] = FAULTS[fault]
    ds, x0, batches = stream(cartpole, backend, u, cache_dir)
    others = np.arange(NBATCH) != FAULTY
    for batch, ref in zip(batches, reference):
        np.testing.assert_array_equal(batch["diverged"].cpu().numpy(), ~others)
        for key in KEYS:
            assert torch.equal(batch[key][others], ref[key][others]), key
        # the simulator reset the faulty trajectory: no NaN or huge value is delivered
        for key in ("state", "sensordata"):
            assert torch.isfinite(batch[key]).all() and batch[key].abs().max() < 1e10, key
    assert ds.stats["diverged"] == NUM_BATCHES
    # before the fault, the faulty trajectory was the clean one
    assert torch.equal(batches[0]["state"][FAULTY, :FAULT_STEP],
                       reference[0]["state"][FAULTY, :FAULT_STEP])
    # the next batch continues the others and restarts the faulty one from its initial state
    for prev, nxt in zip(batches, batches[1:]):
        assert torch.equal(nxt["initial_state"][others], prev["state"][others, -1])
        np.testing.assert_array_equal(nxt["initial_state"][FAULTY].cpu().numpy(),
                                      x0[FAULTY].astype(nxt["initial_state"].cpu().numpy().dtype))
    if backend == "cpu":
        # every batch of the faulty trajectory is what mujoco.rollout gives from the same start
        state, sensordata = rollout.rollout(cartpole, mujoco.MjData(cartpole), x0[[FAULTY]],
                                            u[[FAULTY]], control_spec=SPEC)
        for batch in batches:
            np.testing.assert_array_equal(batch["state"][FAULTY].numpy(), state[0])
            np.testing.assert_array_equal(batch["sensordata"][FAULTY].numpy(), sensordata[0])


MUJOCO_WARNINGS = """
import os, warnings
import numpy as np
import simloader
S = simloader.layout.S
u = np.zeros((8, 5, 3))
u[:, 2, 2] = 1e30  # every trajectory diverges: MuJoCo warns about each one
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=8, nstep=5, nthread=2,
                          control=u, control_spec=int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED),
                          num_batches=3)
with warnings.catch_warnings(record=True) as seen:
    warnings.simplefilter("always")
    flagged = sum(int(b["diverged"].sum()) for b in ds)
said = [str(w.message) for w in seen if "MuJoCo warned" in str(w.message)]
print(flagged, len(said), os.path.exists("MUJOCO_LOG.TXT"))
# simloader's work has ended: MuJoCo's handler is given back, the user's own warnings print
import mujoco, sys
print(mujoco.get_mju_user_warning() is None)
sys.stdout.flush()
m = simloader.load_model("cartpole")
d = mujoco.MjData(m)
d.qfrc_applied[0] = float("nan")
mujoco.mj_step(m, d)
print(os.path.exists("MUJOCO_LOG.TXT"))
"""


def test_mujoco_warnings_are_counted_and_summarised_not_printed(tmp_path, checkout_env):
    """24 diverged trajectories: flagged, one summary warning, no line of MuJoCo's per
    trajectory on stderr and no MUJOCO_LOG.TXT in the working directory; once the stream has
    ended, MuJoCo's handler is given back (the user's own warnings print again)."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-c", MUJOCO_WARNINGS], capture_output=True,
                         text=True, timeout=120, cwd=tmp_path, env=checkout_env())
    assert out.returncode == 0, out.stderr
    # 24 counted while simloader ran; then MuJoCo's own handler again: the user's NaN in
    # their own mj_step reaches stderr and MUJOCO_LOG.TXT, once
    assert out.stdout.split() == ["24", "1", "False", "True", "True"], out.stdout
    assert out.stderr.count("Nan, Inf or huge value") == 1, out.stderr


@pytest.mark.parametrize("backend, pos", [("cpu", "1.5e308"), ("mjx", "2.6e38"),
                                          ("warp", "2.6e38")])
def test_a_trajectory_flagged_for_a_non_finite_record_restarts(backend, pos, monkeypatch):
    # float64 (CPU) overflows past 1.8e308, float32 (MJX, Warp) past 3.4e38
    if backend == "warp":
        pytest.importorskip("warp")
        monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    model = mujoco.MjModel.from_xml_string(FAR_SITE_XML.format(pos=pos))
    x0 = FAR_SITE_X0
    ds = simloader.SimDataset(model, backend=backend, nbatch=8, nstep=6,
                              record=("state", "site_xpos"), continue_episodes=True,
                              num_batches=2, seed=1, control=simloader.controls.Uniform(),
                              initial_state=x0)
    first, second = list(ds)
    # flagged rows start afresh from x0; the others continue where the first batch ended
    flagged = assert_far_site_restarts(first, second, x0)
    assert torch.isfinite(first["state"]).all()
    start = second["initial_state"].cpu().double()
    assert (start[~flagged][:, 0] > 0).all()  # time went on
