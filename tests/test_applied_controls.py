"""What a batch says about its controls: bad controls flagged, the applied (clamped) values
reported, and no delivered tensor shared with the simulator's inputs.

MuJoCo clamps the `ctrl` of an actuator with `ctrllimited` to its `ctrlrange` before a step
(unless `mjDSBL_CLAMPCTRL` is set) and warns (`mjWARN_BADCTRL`) only about a value that is still
non-finite or beyond mjMAXVAL (1e10) after that: `inf` on a limited actuator acts as the bound,
silently. A batch reports what acted, and flags the trajectory whose input was bad.
"""

import mujoco
import numpy as np
import pytest
import torch

import simloader
from simloader import controls

BACKENDS = ["cpu", "mjx"]

# a slider driven by an unlimited motor, a limited one, one limited by autolimits (ctrlrange
# alone) and one with ctrllimited="false" and a range (not limited); sensors give what acted
XML = """
<mujoco>
  <compiler autolimits="true"/>
  <option timestep="0.01"><flag clampctrl="{clampctrl}"/></option>
  <worldbody>
    <body><joint name="x" type="slide"/><geom size=".1" mass="1"/></body>
  </worldbody>
  <actuator>
    <motor name="free" joint="x" ctrllimited="false"/>
    <motor name="limited" joint="x" ctrllimited="true" ctrlrange="-1 1"/>
    <motor name="auto" joint="x" ctrlrange="-2 3"/>
    <motor name="off" joint="x" ctrllimited="false" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


def model(clampctrl="enable"):
    return mujoco.MjModel.from_xml_string(XML.format(clampctrl=clampctrl))


def first_batch(m, control, backend, **kwargs):
    options = {"nthread": 1} if backend == "cpu" else {}
    ds = simloader.SimDataset(m, backend=backend, nbatch=control.shape[0],
                              nstep=control.shape[1], control=control, num_batches=1,
                              dtype=torch.float64, **options, **kwargs)
    return next(iter(ds))


def applied_by_mujoco(m, control):
    """What acted at every step, from MuJoCo itself: a motor's force is its (clamped) ctrl."""
    out = np.empty_like(control)
    for i, rows in enumerate(control):
        d = mujoco.MjData(m)
        for t, row in enumerate(rows):
            d.ctrl[:] = row
            mujoco.mj_step(m, d)
            out[i, t] = d.actuator_force
    return out


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("column", [0, 1, 2])
@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan, 1e11])
def test_bad_control_flags_its_trajectory(value, column, backend):
    # before the fix: inf or 1e11 on a limited actuator (columns 1, 2) gave diverged=False
    m = model()
    u = np.zeros((3, 4, m.nu))
    u[1, 2, column] = value
    batch = first_batch(m, u, backend)
    assert batch["diverged"].tolist() == [False, True, False]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("clampctrl", ["enable", "disable"])
def test_control_reports_what_acted(clampctrl, backend):
    # before the fix: control=1e6 on a ctrlrange of +-1 was reported as 1e6
    m = model(clampctrl=clampctrl)
    rng = np.random.default_rng(0)
    u = rng.choice([-1e6, -1.5, -0.5, 0.0, 0.7, 2.5, 1e6], size=(3, 5, m.nu))
    batch = first_batch(m, u, backend)
    expected = applied_by_mujoco(m, u)
    assert not batch["diverged"].any()
    # MJX simulates in float32 (delivered here as float64)
    precision = np.float64 if backend == "cpu" else np.float32
    np.testing.assert_array_equal(batch["control"].numpy(), expected.astype(precision))
    if clampctrl == "enable":
        assert batch["control"][..., 1].abs().max() == 1.0
        assert batch["control"][..., 2].max() == 3.0 and batch["control"][..., 2].min() == -2.0
    else:  # mjDSBL_CLAMPCTRL: nothing clamped
        assert batch["control"][..., 2].abs().max() == 1e6


def test_generated_and_default_controls_report_what_acted():
    # a default control (0) outside the ctrlrange acts as the nearest bound
    m = mujoco.MjModel.from_xml_string("""
        <mujoco><worldbody><body><joint name="x" type="slide"/><geom size=".1"/></body>
        </worldbody><actuator><motor joint="x" ctrlrange="1 2"/></actuator></mujoco>""")
    for control in (None, controls.Normal(mean=0.0, std=5.0, clip=False)):
        ds = simloader.SimDataset(m, backend="cpu", nbatch=2, nstep=6, control=control,
                                  num_batches=1, nthread=1)
        u = next(iter(ds))["control"]
        assert u.min() >= 1.0 and u.max() <= 2.0, control


@pytest.mark.parametrize("xp", ["numpy", "jax.numpy"])
def test_helpers_work_on_numpy_and_jax_arrays(xp):
    xp = pytest.importorskip(xp)
    m = model()
    low, high = controls.applied_bounds([m], int(mujoco.mjtState.mjSTATE_CTRL))
    assert low.tolist() == [[-np.inf, -1, -2, -np.inf]] and high.tolist() == [[np.inf, 1, 3,
                                                                               np.inf]]
    u = xp.asarray(np.array([[[5.0, 5.0, 5.0, 5.0]], [[0.0, np.nan, 0.0, 0.0]],
                             [[2e10, 0.0, 0.0, 0.0]]]))
    clamped = controls.clamp_applied(u, low[:, None], high[:, None], xp)
    assert np.asarray(clamped)[0].tolist() == [[5.0, 1.0, 3.0, 5.0]]
    assert np.asarray(controls.bad_controls(u)).tolist() == [False, True, True]


def test_bounds_follow_randomized_ctrlrange_and_model_lists():
    m = model()
    spec = int(mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED)
    ranges = np.tile(m.actuator_ctrlrange, (2, 1, 1))
    ranges[1, 1] = [-0.5, 0.25]
    low, high = controls.applied_bounds([m], spec, ctrlrange=ranges)
    assert low.shape == (2, m.nu + m.nv)
    assert high[:, 1].tolist() == [1.0, 0.25] and high[:, m.nu:].tolist() == [[np.inf]] * 2
    # a randomized ctrlrange on the rollout backend: each trajectory clamps to its own
    from simloader import randomize as dr
    ds = simloader.SimDataset(
        m, backend="cpu", nbatch=64, nstep=2, control=np.full((1, 1, m.nu), 1e6),
        randomize=[dr.set("actuator_ctrlrange", dr.Uniform(0.5, 0.9), on="limited", index=1)],
        num_batches=1, nthread=1)
    batch = next(iter(ds))
    np.testing.assert_array_equal(batch["control"][:, 0, 1],
                                  batch["params"]["actuator_ctrlrange[limited]"][:, 0])


@pytest.mark.parametrize("control", ["fixed", "generator", "none"])
def test_no_delivered_tensor_aliases_simulator_input(control):
    # before the fix: a fixed control array was shared with every batch, so editing one
    # batch in place changed the physics of the next and the control of kept batches
    u = {"fixed": np.full((1, 6, 1), 0.5), "generator": controls.Uniform(),
         "none": None}[control]

    def stream():
        return iter(simloader.SimDataset("cartpole", backend="cpu", nbatch=3, nstep=6,
                                         control=u, num_batches=3, nthread=1,
                                         initial_state=simloader.initial.Perturbed()))

    reference = list(stream())
    it = stream()
    first = next(it)
    kept = {k: v.clone() for k, v in first.items()}
    for value in first.values():  # a consumer that edits its batch in place
        if value.dtype == torch.bool:
            value.logical_not_()
        else:
            value.copy_(value * -3 + 1)
    second = next(it)
    kept_second = {k: v.clone() for k, v in second.items()}
    third = next(it)
    for k in reference[1]:
        assert torch.equal(second[k], reference[1][k]), k
        assert torch.equal(second[k], kept_second[k]), k
        assert torch.equal(third[k], reference[2][k]), k
    assert set(kept) == set(first)
