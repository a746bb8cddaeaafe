"""The rollout backend equals mujoco.rollout bit for bit (reliability check 1 and 3)."""

import mujoco
import numpy as np
import pytest
from mujoco import rollout

import simloader
from simloader import controls

S = mujoco.mjtState
SPECS = {
    "ctrl": S.mjSTATE_CTRL,
    "qfrc_applied": S.mjSTATE_QFRC_APPLIED,
    "xfrc_applied": S.mjSTATE_XFRC_APPLIED,
    "eq_active": S.mjSTATE_EQ_ACTIVE,
    "mocap_pos": S.mjSTATE_MOCAP_POS,
    "mocap_quat": S.mjSTATE_MOCAP_QUAT,
    "ctrl|xfrc_applied": S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED,
    "all user inputs": (S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED | S.mjSTATE_XFRC_APPLIED
                        | S.mjSTATE_EQ_ACTIVE | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT),
}
NBATCH, NSTEP = 6, 40


def random_controls(model, spec, nbatch, nstep, seed=0):
    """Controls that exercise every component: forces, 0/1 equality flags, unit quaternions."""
    rng = np.random.default_rng(seed)
    out = np.empty((nbatch, nstep, mujoco.mj_stateSize(model, int(spec))))
    for comp in simloader.layout.control_layout(model, int(spec)):
        cols = out[..., comp.columns]
        if comp.name == "eq_active":
            cols[...] = rng.integers(0, 2, cols.shape)
        elif comp.name == "mocap_quat":
            q = rng.normal(size=(nbatch, nstep, comp.size // 4, 4))
            cols[...] = (q / np.linalg.norm(q, axis=-1, keepdims=True)).reshape(cols.shape)
        elif comp.name == "mocap_pos":
            cols[...] = rng.uniform(-1, 1, cols.shape) + np.tile([0.5, 0.5, 1.2], comp.size // 3)
        else:
            cols[...] = rng.normal(scale=3.0, size=cols.shape)
        out[..., comp.columns] = cols
    return out


def reference(models, x0, control, spec, nthread=2, nstep=None):
    model = models if isinstance(models, mujoco.MjModel) else models[0]
    return rollout.rollout(models, [mujoco.MjData(model) for _ in range(nthread)],
                           x0, control, control_spec=int(spec), nstep=nstep)


def first_batch(ds):
    return next(iter(ds))


@pytest.mark.parametrize("name", list(SPECS))
def test_each_control_spec_component_bitwise(rich_model, name):
    spec = SPECS[name]
    u = random_controls(rich_model, spec, NBATCH, NSTEP)
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=NBATCH, nstep=NSTEP,
                              control=u, control_spec=int(spec), initial_state="raised",
                              nthread=2)
    batch = first_batch(ds)
    x0 = batch["initial_state"].numpy()
    state, sensordata = reference(rich_model, x0, u, spec)
    np.testing.assert_array_equal(batch["state"].numpy(), state)
    np.testing.assert_array_equal(batch["sensordata"].numpy(), sensordata)
    # the control that acted: MuJoCo clamps ctrl to the (limited) actuators' ctrlrange
    applied = u.copy()
    if spec & S.mjSTATE_CTRL:
        range_ = rich_model.actuator_ctrlrange
        applied[..., :rich_model.nu] = np.clip(u[..., :rich_model.nu], range_[:, 0], range_[:, 1])
        assert not np.array_equal(applied, u)
    np.testing.assert_array_equal(batch["control"].numpy(), applied)
    # the model moved: not a trivially equal pair of constant arrays
    assert np.abs(np.diff(state[:, :, 1:], axis=1)).max() > 1e-4


@pytest.mark.parametrize("nthread", [1, 2, 5])
def test_generated_controls_bitwise_at_any_thread_count(rich_model, nthread):
    control = {"ctrl": controls.Uniform(), "xfrc_applied": controls.Normal(std=5.0, on="ball")}
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED)
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=7, nstep=25,
                              control=control, control_spec=spec, nthread=nthread,
                              initial_state=simloader.initial.Perturbed(), seed=3)
    batch = first_batch(ds)
    state, sensordata = reference(rich_model, batch["initial_state"].numpy(),
                                  batch["control"].numpy(), spec)
    np.testing.assert_array_equal(batch["state"].numpy(), state)
    np.testing.assert_array_equal(batch["sensordata"].numpy(), sensordata)
    # only the ball's six xfrc columns are driven; the other bodies' stay zero
    xfrc = batch["control"].numpy()[..., 2:].reshape(7, 25, rich_model.nbody, 6)
    ball = rich_model.body("ball").id
    assert np.all(xfrc[:, :, ball] != 0)
    assert np.all(np.delete(xfrc, ball, axis=2) == 0)


def test_model_list_bitwise(rich_model):
    spec = mujoco.MjSpec.from_string(__import__("conftest").RICH_XML)
    models = []
    for i in range(NBATCH):
        spec.body("ball").first_geom().size[0] = 0.08 + 0.01 * i
        spec.body("target").pos = [0.5, 0.5, 1.0 + 0.05 * i]  # mocap defaults differ too
        models.append(spec.compile())
    u = random_controls(models[0], S.mjSTATE_CTRL, NBATCH, NSTEP)
    ds = simloader.SimDataset(models[0], backend="cpu", nbatch=NBATCH, nstep=NSTEP,
                              control=u, randomize=models, nthread=2)
    batch = first_batch(ds)
    state, sensordata = reference(models, batch["initial_state"].numpy(), u, S.mjSTATE_CTRL)
    np.testing.assert_array_equal(batch["state"].numpy(), state)
    np.testing.assert_array_equal(batch["sensordata"].numpy(), sensordata)
    assert not np.array_equal(state[0], state[-1])


def test_control_none_leaves_inputs_as_mujoco_rollout(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=NSTEP,
                              control_spec=int(S.mjSTATE_CTRL | S.mjSTATE_MOCAP_POS), nthread=1)
    batch = first_batch(ds)
    state, _ = reference(rich_model, batch["initial_state"].numpy(), None, S.mjSTATE_CTRL,
                         nstep=NSTEP)
    np.testing.assert_array_equal(batch["state"].numpy(), state)
    # the delivered control rows are the inputs that acted: zero ctrl, mocap at its model pose
    expected = np.concatenate([[0.0, 0.0], rich_model.body("target").pos])
    np.testing.assert_array_equal(batch["control"].numpy(), np.broadcast_to(expected, (2, NSTEP, 5)))


def test_continuation_concatenates_to_one_long_rollout(rich_model):
    nchunk, nstep = 4, 30  # the ball lands during the second chunk
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED)
    control = {"ctrl": controls.Uniform(), "xfrc_applied": controls.Normal(std=3.0, on="ball")}
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=5, nstep=nstep,
                              control=control, control_spec=spec, continue_episodes=True,
                              num_batches=nchunk, initial_state=simloader.initial.Perturbed(),
                              nthread=2)
    batches = list(ds)
    assert len(batches) == nchunk
    for prev, nxt in zip(batches, batches[1:]):
        np.testing.assert_array_equal(nxt["initial_state"].numpy(), prev["state"][:, -1].numpy())
    u = np.concatenate([b["control"].numpy() for b in batches], axis=1)
    state, sensordata = reference(rich_model, batches[0]["initial_state"].numpy(), u, spec)
    np.testing.assert_array_equal(np.concatenate([b["state"].numpy() for b in batches], 1), state)
    np.testing.assert_array_equal(
        np.concatenate([b["sensordata"].numpy() for b in batches], 1), sensordata)


def test_without_warmstart_continuation_would_differ(rich_model):
    """Guards the test above: restarting chunks with a zero warmstart is not bit-identical,
    so that test would catch a backend that dropped the solver warmstart."""
    nstep = 45  # the ball lands as the second chunk starts: contacts need the solver
    u = random_controls(rich_model, S.mjSTATE_CTRL, 3, 2 * nstep, seed=1)
    x0 = np.tile(simloader.initial.keyframe_state(rich_model, None), (3, 1))
    full, _ = reference(rich_model, x0, u, S.mjSTATE_CTRL)
    first, _ = reference(rich_model, x0, u[:, :nstep], S.mjSTATE_CTRL)
    second, _ = reference(rich_model, first[:, -1], u[:, nstep:], S.mjSTATE_CTRL)
    assert not np.array_equal(np.concatenate([first, second], 1), full)


def test_fresh_batches_differ_and_repeat_with_seed(rich_model):
    def stream(seed):
        ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=3, nstep=5,
                                  control=controls.Uniform(), num_batches=3, seed=seed,
                                  initial_state=simloader.initial.Perturbed(), nthread=1)
        return [b["state"].numpy().copy() for b in ds]

    a, b, c = stream(0), stream(0), stream(1)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], a[1])
    assert not np.array_equal(a[0], c[0])
