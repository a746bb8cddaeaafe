"""Control generators: statistical checks of each distribution, on NumPy, JAX and torch."""

import math

import mujoco
import numpy as np
import pytest

import simloader
from simloader import controls, draws

S = mujoco.mjtState
N, T = 400, 200


def draw(model, control, spec=int(S.mjSTATE_CTRL), backend="numpy", seed=0, n=N, t=T):
    plan = controls.ControlPlan(model, spec, control, n, t)
    if backend == "numpy":
        out = np.empty((n, t, plan.ncontrol))
        plan.sample_numpy(np.random.SeedSequence(seed), out)
        return out
    if backend == "torch":  # the Warp engine's draws on its device (here the CPU)
        import torch
        out = torch.zeros((n, t, plan.ncontrol), dtype=torch.float32)
        plan.sample_torch(np.random.SeedSequence(seed), out, plan.torch_params(out))
        return out.numpy().astype(np.float64)
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp
    (driver,) = plan.drivers
    params = {k: jnp.asarray(v, jnp.float32) for k, v in driver.params.items()}
    d = draws.JaxDraws(jax.random.key(seed), driver.generator.draws)
    return np.asarray(driver.generator.sample(d, params, (n, t, len(driver.columns))))


BACKENDS = ["numpy", "jax", "torch"]


@pytest.mark.parametrize("backend", BACKENDS)
def test_uniform_within_ctrlrange_and_spread(rich_model, backend):
    u = draw(rich_model, controls.Uniform(), backend=backend)
    for col, (lo, hi) in enumerate(rich_model.actuator_ctrlrange):
        x = u[..., col]
        assert x.min() >= lo and x.max() <= hi
        assert abs(x.mean() - (lo + hi) / 2) < 0.02 * (hi - lo)
        assert abs(x.std() - (hi - lo) / math.sqrt(12)) < 0.02 * (hi - lo)
    assert len(np.unique(u[:, 0, 0])) == N  # distinct per trajectory


def test_uniform_unlimited_actuator_defaults_to_unit_range():
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint name='j'/><geom size='.1'/></body></worldbody>"
        "<actuator><motor joint='j' ctrllimited='false'/></actuator></mujoco>")
    u = draw(model, controls.Uniform())
    assert u.min() >= -1 and u.max() <= 1 and u.min() < -0.99 and u.max() > 0.99


@pytest.mark.parametrize("backend", BACKENDS)
def test_normal_moments_and_clip(rich_model, backend):
    spec = int(S.mjSTATE_QFRC_APPLIED)
    x = draw(rich_model, controls.Normal(std=2.0, mean=1.0), spec, backend)
    assert abs(x.mean() - 1.0) < 0.02 and abs(x.std() - 2.0) < 0.02
    clipped = draw(rich_model, controls.Normal(std=5.0), backend=backend)
    assert clipped[..., 0].min() == -2 and clipped[..., 0].max() == 2  # the shoulder's range


@pytest.mark.parametrize("backend", BACKENDS)
def test_ornstein_uhlenbeck_is_stationary_and_correlated(rich_model, backend):
    tau = 0.05  # ten timesteps of 5 ms
    x = draw(rich_model, controls.OrnsteinUhlenbeck(std=0.5, tau=tau, clip=False),
             backend=backend)[..., 0]
    a = math.exp(-rich_model.opt.timestep / tau)
    assert abs(x[:, 0].std() - 0.5) < 0.05 and abs(x[:, -1].std() - 0.5) < 0.05
    lag1 = np.mean(x[:, 1:] * x[:, :-1]) / np.mean(x * x)
    assert abs(lag1 - a) < 0.01
    lag10 = np.mean(x[:, 10:] * x[:, :-10]) / np.mean(x * x)
    assert abs(lag10 - math.exp(-1)) < 0.03


@pytest.mark.parametrize("backend", BACKENDS)
def test_piecewise_constant_holds(rich_model, backend):
    x = draw(rich_model, controls.PiecewiseConstant(hold=7), backend=backend, t=30)
    blocks = [x[:, i:i + 7] for i in range(0, 30, 7)]
    for block in blocks:
        assert np.all(block == block[:, :1])
    assert not np.array_equal(blocks[0][:, 0], blocks[1][:, 0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_sinusoid_and_chirp(rich_model, backend):
    x = draw(rich_model, controls.Sinusoid(amplitude=0.5, frequency=2.0, offset=0.1),
             backend=backend, t=400)
    assert np.abs(x - 0.1).max() <= 0.5 + 1e-6 and np.abs(x - 0.1).max() > 0.49
    # 2 Hz at 5 ms per step: period of 100 steps
    np.testing.assert_allclose(x[:, 100:], x[:, :-100], atol=1e-3)
    chirp = draw(rich_model, controls.Sinusoid(frequency=1.0, chirp_to=10.0), backend=backend,
                 t=400)
    crossings_early = np.sum(np.diff(np.sign(chirp[:, :100, 0]), axis=1) != 0, axis=1).mean()
    crossings_late = np.sum(np.diff(np.sign(chirp[:, 300:, 0]), axis=1) != 0, axis=1).mean()
    assert crossings_late > 3 * crossings_early


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_named_objects_and_undriven_defaults(rich_model, backend):
    spec = int(S.mjSTATE_XFRC_APPLIED | S.mjSTATE_MOCAP_POS | S.mjSTATE_EQ_ACTIVE)
    if backend == "torch":  # sample_torch leaves undriven columns alone: the engine's defaults
        plan = controls.ControlPlan(rich_model, spec, {"xfrc_applied": controls.Normal(
            std=[10, 0, 0, 0, 0, 0], on="ball")}, 5, 3)
        import torch
        out = torch.as_tensor(np.broadcast_to(plan.default_rows[:, None], (5, 3, plan.ncontrol)),
                              dtype=torch.float64).clone()
        plan.sample_torch(np.random.SeedSequence(0), out, plan.torch_params(out))
        x = out.numpy()
    else:
        x = draw(rich_model, {"xfrc_applied": controls.Normal(std=[10, 0, 0, 0, 0, 0],
                                                               on="ball")}, spec, n=5, t=3)
    comps = {c.name: c for c in simloader.layout.control_layout(rich_model, spec)}
    xfrc = x[..., comps["xfrc_applied"].columns].reshape(5, 3, rich_model.nbody, 6)
    ball = rich_model.body("ball").id
    assert np.all(xfrc[:, :, ball, 0] != 0) and np.all(xfrc[:, :, ball, 1:] == 0)
    assert np.all(np.delete(xfrc, ball, axis=2) == 0)
    np.testing.assert_array_equal(x[..., comps["mocap_pos"].columns],
                                  np.broadcast_to(rich_model.body("target").pos, (5, 3, 3)))
    np.testing.assert_array_equal(x[..., comps["eq_active"].columns], 0)  # active="false"


@pytest.mark.parametrize("on", [None, ["ball"], ["hand", "ball"]])
def test_torch_draws_fill_exactly_the_driven_columns(rich_model, on):
    """The Warp engine's draws land in the driven columns, whether they are one run (written
    through a view) or not (through an index), and nowhere else."""
    import torch
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED)
    gen = controls.Uniform(low=1.0, high=2.0, on=on) if on else controls.Uniform(low=1.0,
                                                                                 high=2.0)
    plan = controls.ControlPlan(rich_model, spec, {"xfrc_applied": gen}, 3, 2)
    (driver,) = plan.drivers
    out = torch.full((3, 2, plan.ncontrol), -7.0)
    plan.sample_torch(np.random.SeedSequence(1), out, plan.torch_params(out))
    driven = np.zeros(plan.ncontrol, bool)
    driven[driver.columns] = True
    assert (out[..., driven] >= 1).all() and (out[..., driven] <= 2).all()
    assert (out[..., ~driven] == -7).all()


def test_from_array_and_constant(rich_model):
    values = np.arange(6.0).reshape(1, 3, 2)
    x = draw(rich_model, controls.FromArray(values), n=4, t=3)
    np.testing.assert_array_equal(x, np.broadcast_to(values, (4, 3, 2)))
    x = draw(rich_model, controls.Constant([0.5, -0.5]), n=4, t=3)
    np.testing.assert_array_equal(x[..., 1], -0.5)
    with pytest.raises(ValueError, match=r"FromArray.values: shape \(1, 5, 2\) does not "
                                         r"broadcast to \(nbatch, nstep, ncolumns\) = \(4, 3, 2\)"):
        draw(rich_model, controls.FromArray(np.zeros((1, 5, 2))), n=4, t=3)


def test_drivers_draw_independent_streams(rich_model):
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED)
    both = draw(rich_model, {"ctrl": controls.Normal(clip=False),
                             "qfrc_applied": controls.Normal()}, spec)
    alone = draw(rich_model, {"ctrl": controls.Normal(clip=False)}, spec)
    # adding a generator for another component leaves the first one's numbers unchanged
    np.testing.assert_array_equal(both[..., :2], alone[..., :2])
