"""`record=("com",)`, the whole model's centre of mass (a kind written once, `records.py`): on
the CPU engine bit for bit what `mj_step` leaves in `MjData.subtree_com[0]`; on MJX and MuJoCo
Warp (its CPU kernels here) within their float32 tolerances of MuJoCo C."""

import os

import mujoco
import numpy as np
import pytest
import torch

import simloader
from simloader import records

# float32 against float64: positions from one state, or two steps (one with contacts; `test_mjx`'s
# ONE_STEP_TOL, which test_warp's records keep)
TOL = 1e-4


# a contact-free arm on a slider and a falling ball: small, quick to compile for MJX
ARM_XML = """
<mujoco model="arm">
  <option timestep="0.01"/>
  <worldbody>
    <body name="cart" pos="0 0 1">
      <joint name="slide" type="slide" axis="1 0 0" damping="0.1"/>
      <geom type="box" size="0.1 0.1 0.05" mass="2"/>
      <body name="upper">
        <joint name="shoulder" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
        <body name="lower" pos="0.4 0 0">
          <joint name="elbow" type="hinge" axis="0 1 0"/>
          <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
        </body>
      </body>
    </body>
    <body name="ball" pos="0.5 0 2"><freejoint/><geom size="0.05" mass="0.5"/></body>
  </worldbody>
  <actuator>
    <motor joint="slide" gear="5"/><motor joint="shoulder"/><motor joint="elbow"/>
  </actuator>
</mujoco>"""


@pytest.fixture(scope="module")
def arm():
    return mujoco.MjModel.from_xml_string(ARM_XML)


def _c_com(model, x0, control, every=1):
    """MuJoCo C: `subtree_com[0]` after every `every`-th step of each trajectory from its
    initial state row (mjSTATE_FULLPHYSICS) under its control rows (ctrl):
    (nbatch, nstep // every, 3)."""
    out = []
    for x, u in zip(x0, control):
        data = mujoco.MjData(model)
        mujoco.mj_setState(model, data, x, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        frames = []
        for t, row in enumerate(u):
            data.ctrl[:] = row
            mujoco.mj_step(model, data)
            if (t + 1) % every == 0:
                frames.append(data.subtree_com[0].copy())
        out.append(frames)
    return np.array(out)


def _batch(model, backend, nbatch, nstep, **kwargs):
    control = np.random.default_rng(0).uniform(-1, 1, (nbatch, nstep, model.nu))
    ds = simloader.SimDataset(model, backend=backend, nbatch=nbatch, nstep=nstep,
                              control=control, record=("com", "subtree_com"), num_batches=1,
                              **kwargs)
    return next(iter(ds))


def _c_of(model, batch, every=1):
    return _c_com(model, batch["initial_state"].cpu().numpy().astype(np.float64),
                  batch["control"].cpu().numpy().astype(np.float64), every)


def test_com_parses_to_the_world_bodys_row_of_subtree_com(rich_model):
    com, = records.parse(rich_model, ("com",))
    assert isinstance(com, records.CentreOfMass)
    assert (com.shape, com.dtype, com.fields()) == ((3,), np.float64, ("subtree_com",))
    assert "'com'" in str(pytest.raises(ValueError, records.parse, rich_model, ("cmo",)).value)


@pytest.mark.parametrize("every", [1, 3])
def test_cpu_com_is_mj_steps_subtree_com_bit_for_bit(arm, every):
    batch = _batch(arm, "cpu", 3, 12, record_every=every)
    want = _c_of(arm, batch, every)
    assert batch["com"].dtype == torch.float64 and batch["com"].shape == (3, 12 // every, 3)
    np.testing.assert_array_equal(batch["com"].numpy(), want)
    # a view of the recorded subtree_com: the world body's row, no copy
    assert torch.equal(batch["com"], batch["subtree_com"][:, :, 0])
    assert np.abs(np.diff(want, axis=1)).max() > 0  # the centre of mass moves


def test_mjx_com_matches_mujoco_c(arm):
    # MJX's reading of the kind (`backends/mjx/observe.py`, what its scan records) on one
    # mjx.Data whose subtree_com MJX computed (kinematics, then com_pos: the part of a step
    # that computes it) from the state MuJoCo C stepped to
    jax = pytest.importorskip("jax")
    mjx = pytest.importorskip("mujoco.mjx")
    from simloader.backends.mjx import observe as mjx_observe
    com, = records.parse(arm, ("com",))
    mjx_observe.check([com], mjx.make_data(arm, impl="jax"))
    data = mujoco.MjData(arm)
    data.ctrl[:] = [1.0, -0.5, 0.3]
    for _ in range(20):
        mujoco.mj_step(arm, data)
    mujoco.mj_forward(arm, data)
    m, d = mjx.put_model(arm, impl="jax"), mjx.put_data(arm, data, impl="jax")
    d = d.replace(subtree_com=d.subtree_com * np.nan)  # MJX's own, not C's, is read
    got = jax.jit(lambda m, d: mjx_observe.value(
        com, m, mjx.com_pos(m, mjx.kinematics(m, d))))(m, d)
    assert got.shape == (3,) and got.dtype == np.float32
    np.testing.assert_allclose(np.asarray(got), data.subtree_com[0], atol=TOL)


def test_warp_com_matches_mujoco_c(rich_model, monkeypatch):
    # the whole engine, on the model test_warp runs (Warp's CPU kernels compiled for it once
    # per machine)
    pytest.importorskip("warp")
    pytest.importorskip("mujoco_warp")
    if not torch.cuda.is_available():
        monkeypatch.setitem(os.environ, "SIMLOADER_WARP_ON_CPU", "1")
    batch = _batch(rich_model, "warp", 2, 2, initial_state="raised")
    assert batch["com"].dtype == torch.float32 and batch["com"].shape == (2, 2, 3)
    np.testing.assert_allclose(batch["com"].cpu().numpy(), _c_of(rich_model, batch),
                               atol=TOL)
