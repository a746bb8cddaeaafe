"""`record=` and `record_every=` on the rollout backend: every recorded value is what a plain
`mj_step` loop leaves in MjData, bit for bit; names are checked; views share memory."""

import mujoco
import numpy as np
import pytest
import torch

import simloader
from simloader import memory, observe
from simloader.batch import Batch
from tests.conftest import RICH_XML

# Boxes and balls tumbling onto a plane and each other (many contacts), two hinged arms with
# actuators, a site with force and accelerometer sensors (which make MuJoCo compute cacc,
# cfrc_int and cfrc_ext at every step).
def _pile_xml():
    bodies = "".join(
        f'<body name="b{i}" pos="{0.15 * (i % 3)} {0.15 * (i // 3)} {0.15 + 0.12 * i}">'
        f'<freejoint/><geom type="{"box" if i % 2 else "sphere"}" size="0.06 0.05 0.04"/></body>'
        for i in range(6))
    return f"""
<mujoco model="pile">
  <option timestep="0.004"/>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 .1"/>
    {bodies}
    <body name="arm" pos="0.2 0.2 0.3">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <site name="tip" pos="0.3 0 0"/>
      <body name="hand" pos="0.3 0 0">
        <joint name="wrist" type="hinge" axis="0 0 1"/>
        <geom type="box" size="0.05 0.05 0.05"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder" joint="shoulder" ctrlrange="-3 3" ctrllimited="true"/>
    <position name="wrist" joint="wrist" kp="2"/>
  </actuator>
  <sensor>
    <force name="tip_force" site="tip"/>
    <accelerometer name="tip_acc" site="tip"/>
    <jointpos name="wrist" joint="wrist"/>
  </sensor>
</mujoco>"""


PILE_XML = _pile_xml()
FIELDS = ("qpos", "xpos", "cfrc_ext", "actuator_force", "sensor:tip_force", "ncon", "time",
          "xquat", "qacc")


def _oracle(model, control, nstep, every, names):
    """A plain mj_step loop per trajectory from the model's defaults, copying each named field
    out of MjData after every `every`-th step: {name: (nbatch, nstep // every, ...)}."""
    out = {n: [] for n in names}
    for u in control:
        data = mujoco.MjData(model)
        frames = {n: [] for n in names}
        for t in range(nstep):
            data.ctrl[:] = u[t]
            mujoco.mj_step(model, data)
            if (t + 1) % every:
                continue
            for n in names:
                if n.startswith("sensor:"):
                    value = data.sensor(n[len("sensor:"):]).data
                elif n == "ncon":
                    value = np.int32(data.ncon)
                else:
                    value = getattr(data, n)
                frames[n].append(np.array(value))
        for n in names:
            out[n].append(np.stack(frames[n]))
    return {n: np.stack(v) for n, v in out.items()}


def _control(model, nbatch, nstep, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, (nbatch, nstep, model.nu))


@pytest.mark.parametrize("xml", [PILE_XML, RICH_XML], ids=["pile", "rich"])
@pytest.mark.parametrize("every", [1, 5])
def test_record_equals_mj_step_loop(xml, every):
    model = mujoco.MjModel.from_xml_string(xml)
    names = FIELDS if xml is PILE_XML else ("qpos", "xpos", "actuator_force", "sensor:ball",
                                             "site_xpos", "ncon")
    nbatch, nstep = 4, 60
    control = _control(model, nbatch, nstep)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep,
                              control=control, record=("state",) + names, record_every=every,
                              num_batches=1, nthread=2)
    batch = next(iter(ds))
    expected = _oracle(model, control, nstep, every, names)
    assert (expected["ncon"] > 0).any()  # contacts happen
    for name in names:
        got = batch[name].numpy()
        assert got.dtype == expected[name].dtype, name
        assert got.shape == (nbatch, nstep // every, *expected[name].shape[2:]), name
        np.testing.assert_array_equal(got, expected[name], err_msg=name)
    if xml is PILE_XML:
        assert np.abs(expected["cfrc_ext"]).max() > 0  # contact forces are really recorded
    # frame j is the state after step (j + 1) * every: every-th rows of the every-step rollout
    full = next(iter(simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep,
                                          control=control, num_batches=1)))
    assert torch.equal(batch["state"], full["state"][:, every - 1::every])
    assert torch.equal(batch["control"], full["control"])  # every step's applied row


@pytest.mark.parametrize("every", [1, 5])
def test_record_continuing_chunks_concatenate(every):
    model = mujoco.MjModel.from_xml_string(PILE_XML)
    nbatch, nstep, nchunk = 3, 20, 3
    # a fixed control array is applied in every batch: the long run repeats it
    chunk = _control(model, nbatch, nstep, seed=1)
    names = ("qpos", "xpos", "cfrc_ext", "actuator_force", "sensor:tip_acc")
    expected = _oracle(model, np.concatenate([chunk] * nchunk, axis=1), nstep * nchunk, every,
                       names)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep,
                              control=chunk, record=names, record_every=every,
                              continue_episodes=True, num_batches=nchunk)
    batches = list(ds)
    for n in names:
        got = np.concatenate([b[n].numpy() for b in batches], axis=1)
        np.testing.assert_array_equal(got, expected[n], err_msg=n)


def test_default_record_keeps_the_batch_of_today(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=5, num_batches=1)
    batch = next(iter(ds))
    assert isinstance(batch, Batch)
    assert list(batch) == ["state", "sensordata", "control", "initial_state", "diverged",
                           "stream", "episode", "initial_first"]
    assert batch["state"].shape == (2, 5, ds.config.nstate)


def test_dtypes_integer_fields_stay_integer(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=4, num_batches=1,
                              record=("qpos", "ncon", "eq_active", "sensor:ball"),
                              dtype=torch.float32)
    batch = next(iter(ds))
    assert batch["qpos"].dtype == torch.float32
    assert batch["sensor:ball"].dtype == torch.float32
    assert batch["ncon"].dtype == torch.int32 and batch["ncon"].shape == (2, 4)
    assert batch["eq_active"].dtype == torch.bool and batch["eq_active"].shape == (2, 4, 1)


def _shares(view, base):
    return (view.untyped_storage().data_ptr() == base.untyped_storage().data_ptr()
            and base.data_ptr() <= view.data_ptr() < base.data_ptr() + base.nbytes)


def test_named_views_share_memory(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=3, nstep=6, num_batches=1,
                              record=("state", "sensordata", "xpos", "actuator_force"),
                              control=simloader.controls.Uniform())
    batch = next(iter(ds))
    nq = rich_model.nq
    qpos = batch.view("qpos")
    assert qpos.shape == (3, 6, nq) and _shares(qpos, batch["state"])
    assert torch.equal(qpos, batch["state"][..., 1:1 + nq])
    ball = batch.view("qpos", "ball")
    assert ball.shape == (3, 6, 7) and torch.equal(ball, batch["state"][..., 1:8])
    assert _shares(ball, batch["state"])
    qvel0 = batch.view("qvel", of="initial_state")
    assert qvel0.shape == (3, rich_model.nv) and _shares(qvel0, batch["initial_state"])
    hand = batch.view("xpos", "hand")
    assert torch.equal(hand, batch["xpos"][:, :, rich_model.body("hand").id])
    assert _shares(hand, batch["xpos"])
    sensor = batch.view("sensor:ball")
    assert torch.equal(sensor, batch["sensordata"][..., 1:4]) and _shares(sensor,
                                                                         batch["sensordata"])
    assert torch.equal(batch.view("sensordata", "ball"), sensor)
    elbow = batch.view("ctrl", "elbow")
    assert torch.equal(elbow, batch["control"][..., 1:2]) and _shares(elbow, batch["control"])
    force = batch.view("actuator_force", "elbow")
    assert force.shape == (3, 6, 1) and _shares(force, batch["actuator_force"])
    # (s_t, a_t, s_t+1) of the ball's position without index arithmetic
    s_next = batch.view("qpos", "ball")
    s0 = batch.view("qpos", "ball", of="initial_state")
    assert s0.shape == (3, 7) and s_next.shape == (3, 6, 7)
    with pytest.raises(KeyError, match=r"'qpos' has no object 'bal' \(did you mean 'ball'\?\)"):
        batch.view("qpos", "bal")
    with pytest.raises(KeyError, match="the batch holds no such part"):
        batch.view("cfrc_ext")


def test_sensor_views_share_the_recorded_sensordata(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=3, num_batches=1,
                              record=("sensordata", "sensor:ball", "sensor:shoulder"))
    batch = next(iter(ds))
    assert _shares(batch["sensor:ball"], batch["sensordata"])
    assert torch.equal(batch["sensor:shoulder"], batch["sensordata"][..., :1])


def test_batch_type_and_views_survive_the_dataloader(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=3, num_batches=2,
                              record=("state", "xpos"))
    # workers first: forking after this process iterated hangs (also on main; see the report)
    for workers in (1, 0):
        loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=workers)
        for batch in loader:
            if workers:  # a worker's batch pickles as an OrderedDict: wrapped again, no copy
                batch = Batch(batch, layout=ds.layout)
            assert isinstance(batch, Batch)
            assert torch.equal(batch.view("xpos", "ball"), batch["xpos"][:, :, 2])
    # a plain dict converts to a Batch without a layout
    assert Batch({"x": torch.zeros(1)}).layout is None


def test_tensordict_without_copies(rich_model):
    tensordict = pytest.importorskip("tensordict")
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=3, num_batches=1,
                              record=("state", "xpos", "sensor:ball", "ncon"))
    batch = next(iter(ds))
    td = tensordict.TensorDict(batch, batch_size=[2])
    assert all(td[k].data_ptr() == batch[k].data_ptr() for k in batch)


def test_record_errors(rich_model):
    def make(**kw):
        args = dict(backend="cpu", nbatch=2, nstep=10)
        args.update(kw)
        return simloader.SimDataset(rich_model, **args)

    with pytest.raises(ValueError, match=r"record: unknown name 'xpso' \(did you mean 'xpos', "
                                         r"'xipos'\?\); valid names: 'state', 'sensordata', "
                                         r"'sensor:NAME'"):
        make(record=("xpso",))
    with pytest.raises(ValueError, match=r"record: the model has no sensor 'bal' \(did you mean "
                                         r"'sensor:ball'"):
        make(record=("sensor:bal",))
    with pytest.raises(ValueError, match="record: contact is a structured array"):
        make(record=("contact",))
    with pytest.raises(ValueError, match="record: efc_J is in MjData's arena"):
        make(record=("efc_J",))
    with pytest.raises(ValueError, match=r"record: mj_step leaves cfrc_ext unset, so it would "
                                         r"hold no values of the simulation: MuJoCo computes it "
                                         r"only when the model has an accelerometer"):
        make(record=("cfrc_ext",))
    with pytest.raises(ValueError, match="record: mj_step leaves qfrc_inverse unset"):
        make(record=("qfrc_inverse",))
    with pytest.raises(ValueError, match="record: 'qpos' is given twice"):
        make(record=("qpos", "qpos"))
    with pytest.raises(TypeError, match="record: expected a sequence of names"):
        make(record="qpos")
    with pytest.raises(ValueError, match="record: expected at least one name"):
        make(record=())
    with pytest.raises(ValueError, match=r"record_every: nstep=10 must be a multiple of "
                                         r"record_every, got record_every=3"):
        make(record_every=3)
    with pytest.raises(ValueError, match="record_every: expected an integer >= 1, got 0"):
        make(record_every=0)


def test_a_batch_too_large_for_memory_is_refused(rich_model):
    with pytest.raises(ValueError, match=r"nbatch, record: a batch needs [\d.]+ GiB each, 3 in "
                                         r"flight .*, more than the .* of host memory available; "
                                         r"use a smaller nbatch \(at most \d+ fits\), a larger "
                                         r"record_every \(now 1\)"):
        simloader.SimDataset(rich_model, backend="cpu", nbatch=10**6, nstep=10**5)


def test_batch_nbytes_counts_shared_sources_once(rich_model):
    obs = observe.parse(rich_model, ("sensordata", "sensor:ball", "xpos", "ncon"))
    nbytes = memory.batch_nbytes(obs, nbatch=2, nframes=5, nstep=10, ncontrol=2, nstate=18)
    expected = 8 * 2 * 5 * (4 + 15) + 4 * 2 * 5 + 8 * 2 * 10 * 2 + 8 * 2 * 18 + 2
    assert nbytes == expected


def test_resume_refuses_another_record(rich_model):
    a = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=4, record=("qpos",))
    b = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=4, record=("xpos",))
    c = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=4, record=("qpos",),
                             record_every=2)
    with pytest.raises(ValueError, match=r"record is \['xpos'\] here but \['qpos'\]"):
        b.load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match="record_every is 2 here but 1"):
        c.load_state_dict(a.state_dict())


def test_describe_lists_recorded_keys(rich_model):
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=2, nstep=4,
                              record=("state", "xpos"), record_every=2)
    text = ds.describe()
    assert "recorded keys (nbatch, nframes=2, ...), every 2 step(s):" in text
    assert "xpos (5, 3): rows of world, target, ball, arm, hand" in text


@pytest.mark.parametrize("case", ["none", "broadcast", "models", "randomized"])
def test_every_kth_frame_of_the_full_record(rich_model, case):
    """record_every=5 gives every fifth frame of record_every=1, for every way of giving
    controls and models, across continuing batches."""
    from simloader import randomize as dr
    kw = {"none": dict(control=None),
          "broadcast": dict(control=np.full((1, 1, 2), 0.3)),
          "models": dict(randomize=[rich_model] * 3, control=simloader.controls.Uniform()),
          "randomized": dict(randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2), on="ball")],
                             control=simloader.controls.Uniform())}[case]
    common = dict(backend="cpu", nbatch=3, nstep=10, record=("qpos", "xpos", "ncon"),
                  num_batches=2, continue_episodes=True, **kw)
    every = list(simloader.SimDataset(rich_model, record_every=5, **common))
    full = list(simloader.SimDataset(rich_model, **common))
    for a, b in zip(every, full):
        for key in ("qpos", "xpos", "ncon"):
            assert torch.equal(a[key], b[key][:, 4::5]), key
        assert torch.equal(a["control"], b["control"])
