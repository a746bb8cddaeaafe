"""Episodes that end (`terminate=`) on MJX (CPU JAX here): the same flags and the same fresh
states as the rules imply, the fresh frames' physics as MuJoCo's within the named float32
tolerance, and episodes that run across batches and resume bit for bit."""

import itertools

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

import simloader
from simloader import controls, initial, seeds, sharding
from simloader import terminate as T

pytest.importorskip("mujoco.mjx")

CONTACT_FREE_TOL = 2e-3  # a contact-free float32 trajectory against float64 MuJoCo, absolute
KINEMATICS_TOL = 1e-4  # a height or an axis from float32 positions, absolute
RULES = [T.Outside("hinge", -0.3, 0.3), T.TimeLimit(40)]
PERTURBED = initial.Perturbed(qpos_std=0.05, qvel_std=0.3)


def cartpole(backend, **kwargs):
    return simloader.SimDataset("cartpole", nbatch=8, nstep=120, seed=5, backend=backend,
                                control=controls.Uniform(), initial_state=PERTURBED,
                                terminate=RULES, **kwargs)


def host(batch):
    """The batch on the CPU (MJX delivers on its device: a GPU's on the GPU machine)."""
    return simloader.Batch({k: v.cpu() for k, v in batch.items() if isinstance(v, torch.Tensor)},
                           layout=batch.layout)


@pytest.fixture(scope="module")
def mjx_batch():
    ds = cartpole("mjx")
    return ds, host(next(iter(ds)))


def resets(first):
    """(row, frame, e): every fresh frame, with its reset's number within the batch."""
    out = []
    for row in range(first.shape[0]):
        for e, frame in enumerate(np.flatnonzero(first[row])):
            out.append((row, int(frame), e))
    return out


def test_the_flags_are_what_the_rules_say(mjx_batch):
    _, batch = mjx_batch
    terminated, truncated, first = (batch[k].numpy() for k in ("terminated", "truncated",
                                                                "first"))
    hinge = batch.view("qpos", "hinge").numpy()[..., 0]
    np.testing.assert_array_equal(terminated, (hinge < -0.3) | (hinge > 0.3))
    np.testing.assert_array_equal(first[:, 1:], (terminated | truncated)[:, :-1])
    assert not first[:, 0].any() and first.sum() >= 8
    # the time limit: 40 steps since the batch's start or the last fresh frame (step 0)
    for row in range(8):
        steps = 0
        for j in range(120):
            steps = 0 if first[row, j] else steps + 1
            assert truncated[row, j] == (steps >= 40), (row, j)
    assert truncated.any()


def test_fresh_states_are_the_generators_draws_as_on_the_cpu_engine(mjx_batch):
    ds, batch = mjx_batch
    shard = sharding.Shard()
    draws = [ds.config.initial.sample(seeds.reset_seed(5, shard, 0, e), 8)
             for e in range(T.FRESH_DRAWS)]
    state = batch["state"].numpy()
    found = resets(batch["first"].numpy())
    for row, frame, e in found:
        np.testing.assert_array_equal(state[row, frame],
                                      draws[e % T.FRESH_DRAWS][row].astype(np.float32))
        assert torch.isnan(batch["control"][row, frame]).all()
    # the CPU engine's e-th fresh state of a row is the same draw
    cpu = host(next(iter(cartpole("cpu"))))
    for row, frame, e in resets(cpu["first"].numpy()):
        np.testing.assert_array_equal(cpu["state"][row, frame].numpy(),
                                      draws[e % T.FRESH_DRAWS][row])


def test_a_fresh_episode_is_mujocos_physics_within_float32(mjx_batch):
    ds, batch = mjx_batch
    model = ds.config.model
    data = mujoco.MjData(model)
    state, sensors = batch["state"].numpy(), batch["sensordata"].numpy()
    control = batch["control"].numpy()
    first = batch["first"].numpy()
    checked = 0
    for row, frame, _ in resets(first):
        stop = next((j for j in range(frame + 1, 120) if first[row, j]), 120)
        x0 = state[row, frame].astype(np.float64)
        # a fresh frame records what mj_forward computes at its state
        mujoco.mj_resetData(model, data)
        mujoco.mj_setState(model, data, x0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(sensors[row, frame], data.sensordata, rtol=0,
                                   atol=CONTACT_FREE_TOL)
        if stop - frame < 2:
            continue
        u = control[row, frame + 1:stop].astype(np.float64)
        want, _ = rollout.rollout(model, data, x0[None], u[None])
        np.testing.assert_allclose(state[row, frame + 1:stop], want[0], rtol=0,
                                   atol=CONTACT_FREE_TOL)
        checked += 1
    assert checked >= 4


# MJX's in the slow runs (24 s of compilation on 2 cores: the suite's time)
@pytest.mark.parametrize("backend", [pytest.param("mjx", marks=pytest.mark.slow), "warp"])
def test_a_walker_falls_by_its_own_kinematics(backend, request):
    if backend == "warp":  # its CPU kernels where no GPU is
        pytest.importorskip("mujoco_warp")
        request.getfixturevalue("warp_on_cpu")
    ds = simloader.SimDataset("examples/models/walker/walker.xml", nbatch=3, nstep=120,
                              seed=1, backend=backend,
                              control=controls.OrnsteinUhlenbeck(std=0.6, tau=0.05),
                              terminate=T.Below("torso", 0.9))
    batch = host(next(iter(ds)))
    model, data = ds.config.model, mujoco.MjData(ds.config.model)
    torso = model.body("torso").id
    terminated, first = batch["terminated"].numpy(), batch["first"].numpy()
    assert terminated.any() and first.any()
    np.testing.assert_array_equal(first[:, 1:], terminated[:, :-1])
    for row, j in itertools.product(range(3), range(120)):
        mujoco.mj_setState(model, data, batch["state"][row, j].numpy().astype(np.float64),
                           mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_kinematics(model, data)
        height = data.xpos[torso, 2]
        if abs(height - 0.9) > KINEMATICS_TOL:
            assert terminated[row, j] == (height < 0.9), (row, j, height)
    # fresh frames restart from the model's default pose
    x0 = batch["initial_state"][0].numpy()
    np.testing.assert_array_equal(batch["state"].numpy()[first], np.broadcast_to(
        x0, (int(first.sum()), x0.size)))


@pytest.mark.parametrize("backend", ["cpu", "mjx", "warp"])
def test_episodes_run_across_batches_and_resume_exactly(backend, request):
    if backend == "warp":  # its CPU kernels where no GPU is
        pytest.importorskip("mujoco_warp")
        request.getfixturevalue("warp_on_cpu")
    def make():
        return simloader.SimDataset("cartpole", nbatch=4, nstep=20, seed=2, backend=backend,
                                    control=controls.Uniform(), continue_episodes=True,
                                    num_batches=4, terminate=T.TimeLimit(30))
    whole = [host(b) for b in make()]
    # 30 steps counted across batches: truncated at frame 9 of the second batch, fresh at
    # frame 10, and again 30 steps later (frame 0 of the fourth batch is step 30: frame 9+1
    # = 10 fresh, then 10..19 of batch 2, 0..19 of batch 3 => truncated at frame 19 of batch 3)
    truncated = torch.cat([b["truncated"] for b in whole], dim=1)
    first = torch.cat([b["first"] for b in whole], dim=1)
    assert torch.equal(torch.nonzero(truncated[0]).ravel(), torch.tensor([29, 60]))
    assert torch.equal(torch.nonzero(first[0]).ravel(), torch.tensor([30, 61]))
    ds = make()
    it = iter(ds)
    next(it)
    state = ds.state_dict()
    resumed = make()
    resumed.load_state_dict(state)
    for got, want in zip(resumed, whole[1:]):
        for key in ("state", "control", "terminated", "truncated", "first"):
            torch.testing.assert_close(got[key].cpu(), want[key], rtol=0, atol=0,
                                       equal_nan=True)


@pytest.mark.slow  # 21 s of MJX compilation on 2 cores; the CPU and Warp engines' run in the suite
def test_a_policy_sees_the_fresh_states():
    from test_terminate import check_closed_loop
    check_closed_loop("mjx")


@pytest.mark.slow  # 27 s of MJX compilation on 2 cores; the CPU engine's runs in the suite
def test_a_callable_ends_episodes_as_a_rule_does_in_the_closed_loop():
    """On MJX a callable runs in the closed loop, after every frame, on the observations the
    policy gets: the same flags, resets and states as the rule it spells."""
    from test_terminate import check_callable
    check_callable("mjx", policy=lambda obs: torch.zeros(4, 1, dtype=obs["state"].dtype,
                                                         device=obs["state"].device),
                   policy_noise=simloader.controls.Normal(std=1.0))
