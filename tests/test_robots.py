"""Twelve MuJoCo Menagerie robots (quadrupeds, humanoids, Cassie, arms, drones), as
tests/robots/make_robots.py keeps them: every mesh, height field and image left out, so that
they load with no asset and no network, each with its LICENSE. On every robot:

- the CPU engine equals `mujoco.rollout` bit for bit, from the robot's initial state under
  random controls;
- MJX's refusal (`refuses_model`, said before anything is compiled) names the collisions and
  contacts MJX does not implement, by geom and body, exactly where MJX's own `put_model` or
  `make_data` raises, and nowhere else;
- `backend="auto"` never picks an engine that refuses the robot, and says why it was passed
  over; `backend="mjx"` asked by name refuses it with a ValueError naming the engines that
  simulate it (never MJX's bare NotImplementedError);
- `simloader info` prints each engine's verdict;
- the Warp engine's buffer calibration finds the most contacts and constraint rows any step
  used, as a step-by-step loop of `mj_step` counts them.
"""

import pathlib
import sys

import mujoco
import numpy as np
import pytest
from mujoco import rollout

import simloader
from simloader import cli, controls

ROBOTS_DIR = pathlib.Path(__file__).parent / "robots"
sys.path.insert(0, str(ROBOTS_DIR))
from make_robots import ROBOTS  # noqa: E402

S = mujoco.mjtState


def load(robot):
    return mujoco.MjModel.from_xml_path(str(ROBOTS_DIR / robot / ROBOTS[robot]))


def mjx_raises(model):
    """MJX's own verdict: the message of what put_model or make_data raises, or None."""
    from mujoco import mjx
    try:
        mjx.put_model(model, impl="jax")
        mjx.make_data(model, impl="jax")
    except NotImplementedError as e:
        return str(e)
    return None


def test_twelve_robots_a_user_knows_and_their_licenses():
    assert len(ROBOTS) >= 8
    for robot in ROBOTS:
        assert (ROBOTS_DIR / robot / "LICENSE").is_file()
        model = load(robot)
        assert model.nu > 0 and model.nmesh == 0  # actuated, and no asset to fetch


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_the_cpu_engine_equals_mujoco_rollout_bit_for_bit(robot):
    model = load(robot)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=3, nstep=25, seed=1, num_batches=1,
                              control=controls.Uniform(), nthread=2)
    batch = next(iter(ds))
    want, _ = rollout.rollout(model, [mujoco.MjData(model) for _ in range(2)],
                              batch["initial_state"].numpy(), batch["control"].numpy(),
                              control_spec=int(S.mjSTATE_CTRL))
    np.testing.assert_array_equal(batch["state"].numpy(), want)
    assert not batch["diverged"].any()


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_warp_calibration_finds_the_most_any_step_used(robot):
    pytest.importorskip("mujoco_warp")
    from simloader.backends.warp import options
    model = load(robot)
    data = mujoco.MjData(model)
    x = np.empty(mujoco.mj_stateSize(model, S.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, data, x, S.mjSTATE_FULLPHYSICS)
    x0 = np.tile(x, (5, 1))  # initial velocities apart, so that the trajectories differ
    x0[:, 1 + model.nq:1 + model.nq + model.nv] += np.random.default_rng(1).normal(
        0, 0.5, (5, model.nv))
    low, high = np.where(model.actuator_ctrllimited[:, None].astype(bool),
                         model.actuator_ctrlrange, [-1.0, 1.0]).T
    controls_ = np.random.default_rng(0).uniform(low, high, (5, options._CALIBRATION_STEPS,
                                                              model.nu))
    most = [0, 0]
    for x_i, u_i in zip(x0, controls_):
        mujoco.mj_setState(model, data, x_i, S.mjSTATE_FULLPHYSICS)
        for u in u_i:
            data.ctrl[:] = u
            mujoco.mj_step(model, data)
            most = [max(most[0], data.ncon), max(most[1], data.nefc)]
    assert options._calibrate(model, x0) == tuple(most)


@pytest.mark.parametrize("robot", list(ROBOTS))
def test_mjx_refuses_exactly_what_mjx_cannot_simulate_naming_the_geoms(robot):
    pytest.importorskip("mujoco.mjx")
    from simloader.backends.mjx import support
    model = load(robot)
    refusal, raised = support.refusal(model), mjx_raises(model)
    assert (refusal is None) == (raised is None), (refusal, raised)
    if refusal is not None:
        assert "geom pair" in refusal and "of body '" in refusal
        if "collisions not implemented" in raised:  # the same pair of types, by name
            kinds = [k.removeprefix("mjtGeom.mjGEOM_").lower() for k in
                     raised.split(")")[0].strip("(").split(", ")]
            assert f"{kinds[0]}-{kinds[1]} collisions" in refusal \
                or f"{kinds[1]}-{kinds[0]} collisions" in refusal


def test_auto_passes_over_a_refusing_engine_and_mjx_by_name_says_who_simulates_it(capsys):
    pytest.importorskip("mujoco.mjx")
    model = load("unitree_go2")  # MJX: cylinder-box collisions, condim 1 under elliptic
    ds = simloader.SimDataset(model, nbatch=4, nstep=2, num_batches=2)
    assert ds.config.backend == "cpu"  # the CPU engine wins here: MJX is not even asked
    with pytest.raises(ValueError, match=r"backend: 'mjx' cannot simulate this model: .*"
                                         r"cylinder-box collisions .* use backend='cpu'"):
        simloader.SimDataset(model, backend="mjx", nbatch=4, nstep=2)
    go1 = load("unitree_go1")  # MJX's make_data raised a bare NotImplementedError for it
    with pytest.raises(ValueError, match=r"frictionless contacts \(condim=1\) under the "
                                         r"elliptic friction cone"):
        simloader.SimDataset(go1, backend="mjx", nbatch=4, nstep=2)
    cli.main(["info", str(ROBOTS_DIR / "unitree_h1" / "scene.xml")])
    out = capsys.readouterr().out
    assert "engines:\n  cpu: accepts\n  mjx: refuses: MJX does not simulate cylinder-box" in out
    cli.main(["info", str(ROBOTS_DIR / "franka_emika_panda" / "scene.xml")])
    assert "  mjx: accepts" in capsys.readouterr().out


def test_auto_asks_the_engine_it_would_choose_and_passes_it_over_when_it_refuses():
    """A contact-free model MJX would win on this machine (a pendulum, 8192 trajectories of an
    endless stream) but cannot simulate (an actuator delay): auto passes MJX over, says why,
    and takes the CPU engine. A model the CPU engine wins is never put to MJX (no JAX)."""
    pytest.importorskip("mujoco.mjx")
    delayed = """<mujoco><worldbody><body><joint name="j"/><geom size=".1"/></body>
    </worldbody><actuator><motor joint="j" delay="0.02" nsample="3"/></actuator></mujoco>"""
    ds = simloader.SimDataset(delayed, nbatch=8192, nstep=100)
    assert ds.config.backend == "cpu"
    assert ("passed over: mjx: refuses this model: MJX does not simulate actuator and sensor "
            "delays") in ds.config.backend_reason
