"""`record_kinematics="frame"`: every recorded field of a frame is what `mj_forward` computes at
the frame's own state (its inputs and warmstart as the step left them), on every engine; the
default keeps `mj_step`'s fields (the state before the step), and the physics is the same
either way.

The CPU engine is checked bit for bit over every field `record=` accepts for a model with
contacts, actuators and position, velocity and acceleration sensors, so a field computed in a
stage `records.ACC_FIELDS` does not name fails here; MJX (on the CPU) and MuJoCo Warp (its CPU
kernels here, the CUDA graph on the GPU machine) within float32 tolerances.
"""

import mujoco
import numpy as np
import pytest
import torch

import simloader
from simloader import controls, identity, records
from simloader import terminate as T

FP = int(mujoco.mjtState.mjSTATE_FULLPHYSICS)
VEL, ACC = int(mujoco.mjtStage.mjSTAGE_VEL), int(mujoco.mjtStage.mjSTAGE_ACC)

# a free box that lands on the floor and an actuated two-link arm, with sensors of every stage
XML = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="box" pos="0 0 0.08">
      <freejoint/>
      <geom type="box" size="0.05 0.05 0.05" mass="0.3"/>
      <site name="imu"/>
    </body>
    <body name="upper" pos="0.5 0 0.5">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <body name="lower" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025"/>
        <site name="tip" pos="0.3 0 0"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder" gear="5" ctrlrange="-1 1"/>
    <motor name="elbow" joint="elbow" gear="3" ctrlrange="-1 1"/>
  </actuator>
  <sensor>
    <framepos name="tip_pos" objtype="site" objname="tip"/>
    <jointpos name="elbow_pos" joint="elbow"/>
    <gyro name="gyro" site="imu"/>
    <velocimeter name="vel" site="imu"/>
    <accelerometer name="acc" site="imu"/>
    <actuatorfrc name="shoulder_force" actuator="shoulder"/>
    <touch name="touch" site="imu"/>
  </sensor>
</mujoco>
"""
# what reads positions and velocities only: the frame's values need mjSTAGE_VEL
VEL_RECORDS = ("xpos", "xquat", "site_xpos", "subtree_com", "cvel", "qfrc_bias", "ncon",
               "actuator_length", "actuator_velocity", "sensor:tip_pos", "sensor:gyro",
               "sensor:vel", "com")


@pytest.fixture(scope="module")
def model():
    return mujoco.MjModel.from_xml_string(XML)


def recordable(model):
    """Every name `record=` accepts for `model` besides the state (a field mj_step leaves
    unset here is refused by parse, and left out)."""
    names = []
    for name in records.recordable_fields():
        # the integrator's factor belongs to the step in either mode: mj_forward leaves it
        if name == "qacc_warmstart" or name in records.INTEGRATOR_FIELDS:
            continue
        try:
            records.parse(model, [name])
        except ValueError:
            continue
        names.append(name)
    return names


def forward_at(model, state, warmstart, ctrl):
    """MjData after mj_forward at `state` (mjSTATE_FULLPHYSICS) with that warmstart and ctrl
    (None: as mj_resetData leaves it)."""
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, np.asarray(state, np.float64), FP)
    data.qacc_warmstart[:] = warmstart
    if ctrl is not None:
        data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    return data


_PARSED = {}


def field_of(data, model, name):
    """What `record=[name]` holds for one frame, from an MjData."""
    key = (id(model), name)  # parsed once: a check reads every field of every frame
    if key not in _PARSED:
        (_PARSED[key],) = records.parse(model, [name])
    r = _PARSED[key]
    return np.asarray(r.value(np, {f: np.asarray(getattr(data, f)) for f in r.fields()}, ()))


def frames_of(batch):
    return {k: v.cpu().numpy() for k, v in batch.items() if isinstance(v, torch.Tensor)}


def check_frames(model, b, names, every=1, atol=0.0):
    """Every frame of every trajectory: each recorded name equals mj_forward's at the frame's
    state (fresh frames: inputs as mj_resetData leaves them). Returns the frames checked."""
    nbatch, nframes = b["state"].shape[:2]
    first = b.get("first", np.zeros((nbatch, nframes), bool))
    checked = 0
    for i in range(nbatch):
        for t in range(nframes):
            ctrl = None if first[i, t] else b["control"][i, (t + 1) * every - 1]
            data = forward_at(model, b["state"][i, t], b["qacc_warmstart"][i, t], ctrl)
            for name in names:
                want = field_of(data, model, name)
                got = b[name][i, t]
                if atol:
                    np.testing.assert_allclose(got, want, rtol=atol, atol=atol,
                                               err_msg=f"{name} at trajectory {i}, frame {t}")
                else:
                    np.testing.assert_array_equal(got, want.reshape(got.shape),
                                                  err_msg=f"{name} at trajectory {i}, frame {t}")
            checked += 1
    return checked


def cpu_dataset(model, kinematics, record, **kw):
    kw = {"nbatch": 3, "nstep": 40, "seed": 3, "control": controls.Uniform(), **kw}
    return simloader.SimDataset(model, backend="cpu", num_batches=1,
                                record=("state", "qacc_warmstart", *record),
                                record_kinematics=kinematics, **kw)


def test_every_recordable_field_of_a_frame_is_mj_forward_of_its_state(model):
    names = recordable(model)
    assert len(names) > 40 and {"qacc", "cacc", "cfrc_ext", "efc_force"} & set(names)
    ds = cpu_dataset(model, "frame", names)
    assert ds.config.frame_stage == ACC  # qacc, actuator_force, the accelerometer
    b = frames_of(next(iter(ds)))
    assert b["ncon"].max() > 0  # the box lands: contact forces are part of it
    assert check_frames(model, b, names) == 3 * 40


def test_the_default_keeps_the_state_before_the_step_and_the_physics_is_the_same(model):
    record = ("xpos", "sensordata", "qacc")
    framed = frames_of(next(iter(cpu_dataset(model, "frame", record))))
    stepped = frames_of(next(iter(cpu_dataset(model, "before_step", record))))
    for key in ("state", "qacc_warmstart", "control"):
        np.testing.assert_array_equal(framed[key], stepped[key])
    # mj_step's xpos is the frame before's: frame t's default is frame t-1's own
    np.testing.assert_array_equal(stepped["xpos"][:, 1:], framed["xpos"][:, :-1])
    assert not np.array_equal(stepped["xpos"], framed["xpos"])


def test_positions_and_velocities_only_take_the_velocity_stage(model):
    ds = cpu_dataset(model, "frame", VEL_RECORDS, nstep=30)
    assert ds.config.frame_stage == VEL
    assert check_frames(model, frames_of(next(iter(ds))), VEL_RECORDS) == 90
    # the state alone, or images, derive nothing
    assert cpu_dataset(model, "frame", ("qpos",)).config.frame_stage is None
    (acc,) = records.parse(model, ["sensor:acc"])
    assert records.frame_stage(model, [acc]) == ACC


def test_episodes_and_record_every_frames_and_fresh_frames(model):
    record = ("xpos", "sensordata", "actuator_force", "site_xpos")
    ds = cpu_dataset(model, "frame", record, nstep=80, record_every=2,
                     terminate=[T.Below("box", 0.2), T.TimeLimit(30)])
    b = frames_of(next(iter(ds)))
    assert b["first"].sum() >= 3
    assert check_frames(model, b, record, every=2) == 3 * 40
    # the rules read the same kinematics: Below is the frame's own box height
    np.testing.assert_array_equal(b["terminated"] & ~b["truncated"],
                                  b["xpos"][:, :, 1, 2] < 0.2)


def test_a_policy_sees_the_frame_it_acts_on(model):
    seen = []

    def policy(obs):
        seen.append(obs["site_xpos"].clone())
        return -0.5 * torch.ones(obs["site_xpos"].shape[0], 2, dtype=torch.float64)

    record = ("site_xpos", "sensordata")
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=12, num_batches=1,
                              record=("state", "qacc_warmstart", *record), policy=policy,
                              record_kinematics="frame")
    b = frames_of(next(iter(ds)))
    assert check_frames(model, b, record) == 24
    # the observation before step t + 1 is frame t's
    for t in range(11):
        np.testing.assert_array_equal(seen[t + 1].numpy(), b["site_xpos"][:, t])


def test_refusals_and_the_fingerprint(model):
    with pytest.raises(ValueError, match=r"record_kinematics: expected one of .*'frame'.*got "
                                         r"'after'"):
        cpu_dataset(model, "after", ("xpos",))
    default = identity.fingerprint(cpu_dataset(model, "before_step", ("xpos",)).config)
    framed = identity.fingerprint(cpu_dataset(model, "frame", ("xpos",)).config)
    assert "record_kinematics" not in default  # fingerprints saved before it stay
    assert framed["record_kinematics"] == "frame"
    a = cpu_dataset(model, "frame", ("xpos",))
    b = cpu_dataset(model, "before_step", ("xpos",))
    with pytest.raises(ValueError, match="record_kinematics"):
        simloader.Mixture({"a": a, "b": b}, pad=True)


def mjx_frames(model, **kwargs):
    return frames_of(next(iter(simloader.SimDataset(
        model, backend="mjx", nbatch=2, nstep=10, seed=3, num_batches=1,
        control=controls.Uniform(), dtype=torch.float64, **kwargs))))


def test_mjx_frames_are_mj_forward_of_their_state(model):
    pytest.importorskip("mujoco.mjx")
    b = mjx_frames(model, record=("state", "qacc_warmstart", "xpos", "sensordata", "qacc"),
                   record_kinematics="frame")
    # float32 physics, and MJX's solver stops at its own tolerance: named tolerances
    check_frames(model, {k: v for k, v in b.items() if k != "qacc"}, ("xpos",), atol=1e-5)
    check_frames(model, b, ("sensordata",), atol=2e-3)


# a second MJX program (24 s of compilation on 2 cores): the CPU and Warp engines' tests of
# the same claim run in the README's command
@pytest.mark.slow
def test_mjx_frame_stage_leaves_the_physics_unchanged(model):
    pytest.importorskip("mujoco.mjx")
    b = mjx_frames(model, record=("state", "xpos"), record_kinematics="frame")
    stepped = mjx_frames(model, record=("state", "xpos"))
    np.testing.assert_array_equal(stepped["state"], b["state"])
    assert np.abs(stepped["xpos"][:, 1:] - b["xpos"][:, 1:]).max() > 1e-3


@pytest.mark.parametrize("record", [("xpos", "site_xpos", "sensor:gyro"),  # mjSTAGE_VEL
                                    ("xpos", "sensordata", "qacc")])  # mjSTAGE_ACC
def test_warp_frames_are_mj_forward_of_their_state(model, record, warp_on_cpu):
    """MuJoCo Warp's CPU kernels here, its captured CUDA graph on the GPU machine: the pass
    after the step (`step1` or `forward`) runs inside the step, the physics unchanged."""
    pytest.importorskip("mujoco_warp")
    kw = dict(backend="warp", nbatch=2, nstep=12, seed=3, num_batches=1,
              control=controls.Uniform(), naconmax=64, njmax=128)
    ds = simloader.SimDataset(model, record=("state", "qacc_warmstart", *record),
                              record_kinematics="frame", **kw)
    assert ds.config.frame_stage == (ACC if "qacc" in record else VEL)
    b = {k: v.cpu().double() for k, v in frames_of_device(next(iter(ds))).items()}
    b = {k: v.numpy() for k, v in b.items()}
    # float32 physics: named tolerances (qacc is a solver's output: looser)
    check_frames(model, b, [r for r in record if r not in ("sensordata", "qacc")], atol=2e-5)
    if "sensordata" in record:
        check_frames(model, b, ("sensordata",), atol=5e-3)
    stepped = frames_of_device(next(iter(simloader.SimDataset(
        model, record=("state", "xpos"), **kw))))
    np.testing.assert_allclose(stepped["state"].cpu().double().numpy(), b["state"], atol=1e-5)
    assert np.abs(stepped["xpos"].cpu().double().numpy()[:, 1:] - b["xpos"][:, 1:]).max() > 1e-3


def frames_of_device(batch):
    return {k: v for k, v in batch.items() if isinstance(v, torch.Tensor)}
