"""Episodes that end where the task ends (`terminate=`), on the CPU engine: every episode of a
batch equals `mujoco.rollout` from its initial state with its controls, bit for bit; the
flags are what the rules say; the fresh frames are fresh initial states."""

import math

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

import simloader
from simloader import controls, initial
from simloader import terminate as T

WALKER = "examples/models/walker/walker.xml"


def episodes(batch, row):
    """[(start frame, stop frame)] of trajectory `row`: the frames of each episode."""
    first = batch["first"][row].numpy()
    starts = [0] + list(np.flatnonzero(first))
    stops = starts[1:] + [first.shape[0]]
    return list(zip(starts, stops))


def check_against_rollout(ds, batch, rows):
    """Every episode of `rows` equals mujoco.rollout from its initial state (the batch's
    initial state, or its fresh first frame) with its controls, state and sensors bit for
    bit; a fresh frame's sensors are mj_forward's at it; its controls are NaN."""
    model = ds.config.model
    data = mujoco.MjData(model)
    state = batch["state"].numpy()
    sensors = batch["sensordata"].numpy()
    control = batch["control"].numpy()
    checked = 0
    for row in rows:
        for start, stop in episodes(batch, row):
            if start == 0:
                x0, frames = batch["initial_state"][row].numpy(), range(0, stop)
            else:
                x0, frames = state[row, start], range(start + 1, stop)
                # the fresh frame: its sensors as mj_forward computes them there
                mujoco.mj_resetData(model, data)
                mujoco.mj_setState(model, data, x0, mujoco.mjtState.mjSTATE_FULLPHYSICS)
                mujoco.mj_forward(model, data)
                np.testing.assert_array_equal(sensors[row, start], data.sensordata)
                assert np.isnan(control[row, start]).all()
            if len(frames) == 0:
                continue
            u = control[row, frames.start:frames.stop]
            assert np.isfinite(u).all()
            want_state, want_sensors = rollout.rollout(model, data, x0[None], u[None])
            np.testing.assert_array_equal(state[row, frames.start:frames.stop], want_state[0])
            np.testing.assert_array_equal(sensors[row, frames.start:frames.stop],
                                          want_sensors[0])
            checked += 1
    return checked


@pytest.fixture(scope="module")
def walker():
    ds = simloader.SimDataset(WALKER, nbatch=6, nstep=300, seed=1, backend="cpu",
                              control=controls.OrnsteinUhlenbeck(std=0.6, tau=0.05),
                              initial_state=initial.Perturbed(qpos_std=0.05, qvel_std=0.2),
                              terminate=T.Below("torso", 0.9))
    return ds, next(iter(ds))


def test_every_walker_episode_equals_mujoco_rollout(walker):
    # contacts and the constraint solver's warmstart: a reset that kept the fallen walker's
    # warmstart (or applied its control row) would not equal a rollout from the fresh state
    ds, batch = walker
    assert batch["first"].sum() >= 6, "every walker falls and restarts at least once"
    assert check_against_rollout(ds, batch, range(6)) > 12


def test_the_flags_say_what_the_rule_and_the_resets_did(walker):
    ds, batch = walker
    model = ds.config.model
    data = mujoco.MjData(model)
    terminated, first = batch["terminated"].numpy(), batch["first"].numpy()
    assert not batch["truncated"].any()  # no time limit
    torso = model.body("torso").id
    for row in range(2):
        for j in range(batch["state"].shape[1]):
            mujoco.mj_setState(model, data, batch["state"][row, j].numpy(),
                               mujoco.mjtState.mjSTATE_FULLPHYSICS)
            mujoco.mj_kinematics(model, data)
            assert terminated[row, j] == (data.xpos[torso, 2] < 0.9)
    # the frame after a terminated one is a fresh one, and only then
    np.testing.assert_array_equal(first[:, 1:], terminated[:, :-1])
    assert not first[:, 0].any()


def test_a_free_bodys_height_is_its_qpos_column_read_without_kinematics():
    # mj_kinematics copies a free joint's position into xpos: the humanoid's torso (a free
    # joint alone) is read from qpos, by every engine, with no kinematics; the walker's torso
    # (slide and hinge joints) and the humanoid's head (under the torso) from xpos
    humanoid = simloader.load_model("humanoid")
    walker = mujoco.MjModel.from_xml_path(WALKER)
    torso = T.parse(humanoid, T.Below("torso", 0.9))
    assert torso.reads == ("qpos",) and not torso.kinematic
    assert T.parse(humanoid, T.Below("head", 1.2)).reads == ("xpos",)
    assert T.parse(walker, T.Below("torso", 0.9)).kinematic
    rule = torso.rules[0]
    # derived from the model: not in a stream's fingerprint (stores and checkpoints saved
    # before the column was read still resume)
    from simloader import identity
    assert set(identity._describe(rule)) == {"type", "body", "height", "body_id"}
    ds = simloader.SimDataset(humanoid, nbatch=4, nstep=150, seed=3, backend="cpu",
                              control=controls.Uniform())
    states = next(iter(ds))["state"].numpy().reshape(-1, ds.config.nstate)
    data = mujoco.MjData(humanoid)
    heights = []
    for row in states:
        mujoco.mj_setState(humanoid, data, row, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_kinematics(humanoid, data)
        heights.append(data.xpos[humanoid.body("torso").id, 2])
    qpos = states[:, 1:1 + humanoid.nq]
    np.testing.assert_array_equal(qpos[:, rule.free_z], heights)  # the same number, not close
    met = rule.met(np, {"qpos": qpos})
    np.testing.assert_array_equal(met, np.array(heights) < 0.9)
    assert met.any() and not met.all()  # the humanoid falls: both verdicts are seen


def test_fresh_states_come_from_the_generator_seeded_per_row_and_episode(walker):
    ds, batch = walker
    again = next(iter(simloader.SimDataset(
        WALKER, nbatch=6, nstep=300, seed=1, backend="cpu",
        control=controls.OrnsteinUhlenbeck(std=0.6, tau=0.05),
        initial_state=initial.Perturbed(qpos_std=0.05, qvel_std=0.2),
        terminate=T.Below("torso", 0.9))))
    for key in ("state", "sensordata", "first", "terminated"):
        assert torch.equal(batch[key], again[key])
    fresh = batch["state"][batch["first"]]
    assert len(torch.unique(fresh[:, 1:], dim=0)) == len(fresh)  # each its own draw
    # drawn around the model's default pose (time 0, rootz 0)
    assert torch.all(fresh[:, 0] == 0)


def test_a_fixed_initial_state_restarts_from_itself_and_record_every():
    ds = simloader.SimDataset("cartpole", nbatch=5, nstep=400, seed=0, backend="cpu",
                              record_every=2, control=controls.Uniform(),
                              terminate=[T.Outside("hinge", -0.25, 0.25)])
    batch = next(iter(ds))
    first = batch["first"]
    assert first.sum() >= 5
    state = batch["state"].numpy()
    np.testing.assert_array_equal(state[first.numpy()],
                                  np.broadcast_to(batch["initial_state"][0].numpy(),
                                                  (int(first.sum()), state.shape[-1])))
    # a fresh frame's two control rows are NaN, and only those
    nan = torch.isnan(batch["control"][..., 0]).reshape(5, -1, 2)
    assert torch.equal(nan[..., 0], first) and torch.equal(nan[..., 1], first)
    hinge = batch.view("qpos", "hinge").numpy().reshape(5, 200)
    np.testing.assert_array_equal(batch["terminated"].numpy(),
                                  (hinge < -0.25) | (hinge > 0.25))


def test_a_time_limit_truncates_every_k_steps():
    ds = simloader.SimDataset("cartpole", nbatch=3, nstep=50, seed=0, backend="cpu",
                              control=controls.Uniform(), terminate=T.TimeLimit(10))
    batch = next(iter(ds))
    truncated, first = batch["truncated"].numpy(), batch["first"].numpy()
    # steps 1..10 then a fresh frame (step 0), 10 more: frames 9, 20, 31, 42
    want = np.zeros(50, dtype=bool)
    want[[9, 20, 31, 42]] = True
    for row in range(3):
        np.testing.assert_array_equal(truncated[row], want)
        np.testing.assert_array_equal(first[row, 1:], want[:-1])
    assert not batch["terminated"].any()
    assert check_against_rollout(ds, batch, range(3)) == 15


def test_tilted_reads_the_bodys_orientation():
    ds = simloader.SimDataset(WALKER, nbatch=4, nstep=200, seed=2, backend="cpu",
                              control=controls.Uniform(), terminate=T.Tilted("torso", 0.5))
    batch = next(iter(ds))
    model, data = ds.config.model, mujoco.MjData(ds.config.model)
    torso = model.body("torso").id
    seen = 0
    for j in range(200):
        mujoco.mj_setState(model, data, batch["state"][0, j].numpy(),
                           mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_kinematics(model, data)
        tilt = math.acos(min(1.0, data.xmat[torso, 8]))
        assert bool(batch["terminated"][0, j]) == (tilt > 0.5)
        seen += tilt > 0.5
    assert seen >= 1
    assert check_against_rollout(ds, batch, range(4)) >= 4


def test_without_terminate_nothing_changes():
    ds = simloader.SimDataset("cartpole", nbatch=2, nstep=5, seed=0, backend="cpu")
    assert not {"terminated", "truncated", "first"} & set(next(iter(ds)))


@pytest.mark.parametrize("rule, message", [
    (T.Below("nobody", 0.5), "terminate: Below('nobody', 0.5): the model has no body 'nobody'"),
    (T.Outside("nohinge", -1, 1), "the model has no joint 'nohinge' (did you mean 'hinge'?); its joints: ['slider', 'hinge']"),
    (T.Outside("rootz", -1, 1), None),
])
def test_unknown_names_are_refused_with_the_choices(rule, message):
    if message is None:  # a walker's slide joint is 1-dof: accepted
        simloader.SimDataset(WALKER, nbatch=1, nstep=1, backend="cpu", terminate=rule)
        return
    with pytest.raises(ValueError) as e:
        simloader.SimDataset("cartpole", nbatch=1, nstep=1, backend="cpu", terminate=rule)
    assert message in str(e.value)


def test_bad_rules_are_refused_at_construction():
    with pytest.raises(ValueError, match=r"max_angle must be in \(0, pi\] radians, got 4"):
        T.Tilted("torso", 4)
    with pytest.raises(ValueError, match=r"max_angle must be in \(0, pi\] radians, got 0"):
        T.Tilted("torso", 0)
    T.Below("torso", -0.5)  # a negative height is fine
    with pytest.raises(ValueError, match=r"TimeLimit\(steps\)'s steps must be an int >= 1, got 0"):
        T.TimeLimit(0)
    with pytest.raises(ValueError, match="expected low < high"):
        T.Outside("hinge", 1, -1)
    with pytest.raises(ValueError, match="at most one TimeLimit"):
        simloader.SimDataset("cartpole", nbatch=1, nstep=1, backend="cpu",
                             terminate=[T.TimeLimit(3), T.TimeLimit(4)])
    with pytest.raises(TypeError, match="terminate: expected None, a rule"):
        simloader.SimDataset("cartpole", nbatch=1, nstep=1, backend="cpu", terminate="hinge")


def test_a_free_joint_is_not_outsideable():
    xml = """<mujoco><worldbody><body name="b"><freejoint name="f"/><geom size="0.1"/></body>
             </worldbody></mujoco>"""
    with pytest.raises(ValueError, match="joint 'f' is a free joint; Outside takes a 1-dof"):
        simloader.SimDataset(xml, nbatch=1, nstep=1, backend="cpu",
                             terminate=T.Outside("f", -1, 1))


SEEN: list = []  # what Recorder was given (simloader runs a copy of the policy)


class Recorder(torch.nn.Module):
    """A linear policy on the state that keeps every observation it was given."""

    def forward(self, obs):
        SEEN.append(obs["state"].clone())
        return torch.tanh(3 * obs["state"][:, 2:3] + obs["state"][:, 4:5]).to(obs["state"].dtype)


def check_closed_loop(backend):
    """A policy in the loop with episodes: every CPU episode is mujoco.rollout's with the
    controls that acted, and the policy sees each fresh state."""
    policy = Recorder()
    SEEN.clear()
    ds = simloader.SimDataset("cartpole", nbatch=4, nstep=150, seed=0, backend=backend,
                              policy=policy, policy_noise=controls.Normal(std=0.8),
                              terminate=[T.Outside("hinge", -0.2, 0.2), T.TimeLimit(60)])
    batch = {k: v.cpu() if isinstance(v, torch.Tensor) else v
             for k, v in next(iter(ds)).items()}
    first = batch["first"]
    assert first.sum() >= 4
    assert torch.equal(first[:, 1:], (batch["terminated"] | batch["truncated"])[:, :-1])
    # call t + 1 sees frame t: at a fresh frame, the fresh state
    seen = torch.stack(SEEN[:151], dim=1).cpu()
    for row, frame in torch.nonzero(first).tolist():
        torch.testing.assert_close(seen[row, frame + 1], batch["state"][row, frame])
        assert torch.isnan(batch["control"][row, frame]).all()
    return ds, batch


def test_a_policy_sees_the_fresh_states_and_episodes_stay_physics():
    ds, batch = check_closed_loop("cpu")
    assert check_against_rollout(ds, batch, range(4)) >= 8


def test_a_fresh_frames_image_shows_its_fresh_state():
    from simloader import render
    try:
        render.gl_platform()
    except RuntimeError as e:
        pytest.skip(f"no OpenGL here: {e}")
    ds = simloader.SimDataset("cartpole", nbatch=3, nstep=80, seed=0, backend="cpu",
                              control=controls.Uniform(),
                              record=("state", simloader.Camera(-1, height=24, width=32)),
                              terminate=T.Outside("hinge", -0.2, 0.2))
    batch = next(iter(ds))
    first = batch["first"]
    assert first.any()
    images = batch["camera/free/rgb"][first]
    # a fixed initial state: every fresh frame is the same state, so the same picture, which
    # differs from the terminated frame before it
    assert all(torch.equal(image, images[0]) for image in images)
    row, frame = (int(i) for i in torch.nonzero(first)[0])
    assert not torch.equal(batch["camera/free/rgb"][row, frame - 1], images[0])
    model = ds.config.model
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, batch["initial_state"][0].numpy(),
                       mujoco.mjtState.mjSTATE_FULLPHYSICS)
    mujoco.mj_forward(model, data)
    with render.Renderers(model, ds.config.observations[1:]) as renderers:
        out = {"camera/free/rgb": np.zeros((1, 1, 24, 32, 3), np.uint8)}
        rows = np.empty((1, 1, mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_INTEGRATION)))
        mujoco.mj_getState(model, data, rows[0, 0], mujoco.mjtState.mjSTATE_INTEGRATION)
        renderers.draw([0], rows, lambda i: model, out)
    np.testing.assert_array_equal(images[0].numpy(), out["camera/free/rgb"][0, 0])


def hinge_out(obs):
    """A callable terminate=: the pole past 0.25 rad (the state's columns: time, slider,
    hinge, ...)."""
    return obs["state"][:, 2].abs() > 0.25


def check_callable(backend, **kwargs):
    """A callable over the observations ends episodes as the same rule does."""
    kwargs = kwargs or {"control": controls.Uniform()}
    make = lambda terminate: simloader.SimDataset(  # noqa: E731
        "cartpole", nbatch=4, nstep=120, seed=3, backend=backend, terminate=terminate,
        **kwargs)
    by_callable = next(iter(make(hinge_out)))
    by_rule = next(iter(make(T.Outside("hinge", -0.25, 0.25))))
    assert by_callable["first"].sum() >= 4
    for key in ("state", "terminated", "truncated", "first"):
        assert torch.equal(by_callable[key].cpu(), by_rule[key].cpu()), key


def test_a_callable_ends_episodes_as_a_rule_does():
    check_callable("cpu")
    check_callable("cpu", policy=lambda obs: torch.zeros(4, 1, dtype=obs["state"].dtype),
                   policy_noise=controls.Normal(std=1.0))


def test_a_callable_of_the_wrong_shape_is_refused_at_its_first_call():
    ds = simloader.SimDataset("cartpole", nbatch=4, nstep=10, backend="cpu",
                              terminate=lambda obs: obs["state"][:, 2])
    with pytest.raises(ValueError, match=r"must return a bool tensor of shape \(4,\) .* got "
                                         r"torch.float64 tensor of shape \(4,\) at frame 0"):
        next(iter(ds))


def test_mjx_refuses_a_callable_in_its_open_loop_by_name():
    pytest.importorskip("mujoco.mjx")
    with pytest.raises(ValueError, match=r"terminate: a callable over the observations runs "
                                         r"where the simulation steps from Python: on MJX, the "
                                         r"closed loop \(policy=\)"):
        simloader.SimDataset("cartpole", nbatch=4, nstep=5, backend="mjx", terminate=hinge_out)


SEEN_OBS: list = []  # what WalkerPolicy was given


class WalkerPolicy(torch.nn.Module):
    """Zero controls; keeps every observation it was given."""

    def forward(self, obs):
        SEEN_OBS.append({k: v.clone() for k, v in obs.items()})
        return torch.zeros(obs["state"].shape[0], 6, dtype=obs["state"].dtype,
                           device=obs["state"].device)


@pytest.mark.parametrize("backend", ["cpu", "warp"])
def test_a_body_rule_leaves_a_policys_observations_as_they_are(backend, request):
    # a body rule computes the kinematics of each frame's own state; what the policy sees
    # after a step stays what mj_step left (xpos of the step's start, every sensor current),
    # as the frame records it and as a stream without the rule shows it
    if backend == "warp":
        pytest.importorskip("mujoco_warp")
        request.getfixturevalue("warp_on_cpu")
    SEEN_OBS.clear()
    ds = simloader.SimDataset(WALKER, nbatch=3, nstep=80, seed=2, backend=backend,
                              record=("state", "sensordata", "xpos"), policy=WalkerPolicy(),
                              policy_noise=controls.Normal(std=0.8),
                              terminate=T.Below("torso", 0.9))
    batch = next(iter(ds))
    assert batch["first"].any()
    for t in range(79):  # (the policy picks no row after the last step)
        for key in ("state", "sensordata", "xpos"):
            torch.testing.assert_close(SEEN_OBS[t + 1][key].cpu(), batch[key][:, t].cpu(),
                                       rtol=0, atol=0, msg=f"{key} after step {t}")


@pytest.mark.parametrize("rule, message", [
    (T.Below("world", 0.1), r"terminate: Below\('world', 0.1\): body 'world' is the world "
                            r"body, which never moves \(its height is always 0\): name a body "
                            r"that moves \(the model's other bodies: \['cart', 'pole'\]\)"),
    (T.Tilted("world", 1.0), r"terminate: Tilted\('world', 1.0\): body 'world' is the world "
                             r"body, which never moves \(its tilt is always 0\)"),
], ids=["Below", "Tilted"])
def test_a_body_rule_on_the_world_body_is_refused(rule, message):
    with pytest.raises(ValueError, match=message):
        simloader.SimDataset("cartpole", nbatch=1, nstep=1, backend="cpu", terminate=rule)


@pytest.mark.parametrize("terminate, message", [
    (T.Below, r"terminate: got the class Below, expected an instance such as "
              r"Below\('torso', 0.8\)"),
    ([T.Outside, T.TimeLimit(5)], r"terminate: got the class Outside, expected an instance such "
                                  r"as Outside\('hinge', -0.2, 0.2\)"),
    (T.TimeLimit, r"got the class TimeLimit, expected an instance such as TimeLimit\(500\)"),
    (torch.nn.Identity, r"terminate: got the class Identity, expected an instance \(a rule of "
                        r"simloader.terminate or a callable obs -> \(nbatch,\) bool tensor\), "
                        r"not its class"),
], ids=["Below", "in-a-list", "TimeLimit", "not-a-rule"])
def test_a_class_given_for_a_rule_is_refused_at_construction(terminate, message):
    with pytest.raises(TypeError, match=message):
        simloader.SimDataset("cartpole", nbatch=1, nstep=1, backend="cpu", terminate=terminate)


@pytest.mark.parametrize("verdict, got", [
    # a bool tensor of the right shape, elsewhere: the engine could not combine it
    (lambda obs: torch.zeros(4, dtype=torch.bool, device="meta"),
     r"got torch.bool tensor of shape \(4,\) on meta at frame 0"),
    (lambda obs: obs["state"][:, 2:3].abs() > 0.25, r"got torch.bool tensor of shape \(4, 1\) "
                                                    r"at frame 0"),
    (lambda obs: bool(obs["state"][0, 2] > 0), r"got bool at frame 0"),
], ids=["meta", "shape", "not-a-tensor"])
def test_a_callables_verdict_not_a_bool_tensor_here_is_refused_at_its_first_call(verdict, got):
    ds = simloader.SimDataset("cartpole", nbatch=4, nstep=3, backend="cpu", terminate=verdict)
    with pytest.raises(ValueError, match=r"terminate: the callable '<lambda>' must return a bool "
                                         r"tensor of shape \(4,\) on cpu \(the observations' "
                                         r"device\) \(nbatch: does each trajectory's episode "
                                         r"end\?\), " + got):
        next(iter(ds))
