"""The MJX side of `record=`: each observation's MJX value (`backends/mjx/observe.py`) on one mjx.Data against MuJoCo C
after the same steps (float32, named tolerances), and the host-side refusals."""

import mujoco
import numpy as np
import pytest
import torch

from simloader import memory, observe, rules
from tests.test_record import PILE_XML

jax = pytest.importorskip("jax")
mjx = pytest.importorskip("mujoco.mjx")
from simloader.backends.mjx import observe as mjx_observe  # noqa: E402
jnp = jax.numpy

# after one contact step from the same state (reliability check 2: 1e-4); forces are larger
# numbers, compared relative to their scale
ONE_STEP_ATOL = 1e-4
FORCE_RTOL = 2e-3
NAMES = ("state", "qpos", "qvel", "xpos", "xquat", "xmat", "geom_xmat", "site_xpos", "actuator_force", "cfrc_ext",
         "sensor:tip_acc", "sensor:wrist", "sensordata", "time")


def test_jax_values_match_mujoco_c_after_a_contact_step():
    model = mujoco.MjModel.from_xml_string(PILE_XML)
    data = mujoco.MjData(model)
    for _ in range(60):  # let the pile land: contacts
        data.ctrl[:] = [1.0, 0.5]
        mujoco.mj_step(model, data)
    assert data.ncon > 0
    observations = observe.parse(model, NAMES)
    mjx_observe.check(observations, mjx.make_data(model, impl="jax"))
    m = mjx.put_model(model, impl="jax")
    d = mjx.put_data(model, data, impl="jax")
    mujoco.mj_step(model, data)
    # the step is this test's harness, not what it checks: compiled without XLA's backend
    # optimizations (half the compile time of the pile's collisions on a CPU, the same math)
    step = jax.jit(mjx.step).lower(m, d).compile(
        compiler_options={"xla_backend_optimization_level": 0})
    d = step(m, d)
    values = jax.jit(lambda m, d: {o.key: mjx_observe.value(o, m, d) for o in observations})(m, d)
    for o in observations:
        got = np.asarray(values[o.key])
        if isinstance(o, observe.State):
            expected = np.empty(o.shape)
            mujoco.mj_getState(model, data, expected, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        elif o.key.startswith("sensor:"):
            expected = data.sensor(o.key[len("sensor:"):]).data
        else:
            expected = np.asarray(getattr(data, o.key))
        assert got.shape == o.shape, o.key
        assert got.dtype == np.float32, o.key
        scale = max(1.0, float(np.abs(expected).max(initial=0)))
        tol = FORCE_RTOL * scale if o.key in ("cfrc_ext", "sensor:tip_acc", "sensordata",
                                              "actuator_force") else ONE_STEP_ATOL
        np.testing.assert_allclose(got, expected, atol=tol, rtol=0, err_msg=o.key)


def test_jax_values_under_vmap_have_the_frame_shape():
    model = mujoco.MjModel.from_xml_string(PILE_XML)
    observations = observe.parse(model, ("xpos", "sensor:tip_force", "state", "time"))
    m = mjx.put_model(model, impl="jax")
    d = jax.vmap(lambda _: mjx.make_data(model, impl="jax"))(np.arange(3))
    values = mjx_observe.frame(observations, None, m, d)
    assert sorted(values) == sorted(o.key for o in observations)  # (JAX sorts dict keys)
    for o in observations:
        assert values[o.key].shape == (3, *o.shape), o.key
    floating = [o.key for o in observations if o.floating]
    assert rules.finite([values[k] for k in floating], jnp).tolist() == [True] * 3
    values["xpos"] = values["xpos"].at[1, 2, 0].set(np.nan)
    values["time"] = values["time"].at[2].set(np.inf)
    assert rules.finite([values[k] for k in floating], jnp).tolist() == [True, False, False]
    assert rules.finite([], jnp) is None


def test_a_batch_too_large_for_the_gpu_is_refused(rich_model):
    import simloader
    ds = simloader.SimDataset(rich_model, backend="cpu", nbatch=1024, nstep=1000,
                              record=("state", "xpos"), record_every=2)
    # what the MJX backend calls with its device's free memory, floats as float32
    with pytest.raises(ValueError, match=r"nbatch, record: a batch needs 72.3 MiB, more than "
                                         r"the 10.0 MiB of GPU memory available; use a smaller "
                                         r"nbatch \(at most 141 fits\), a larger record_every "
                                         r"\(now 2\)"):
        memory.check_batch_fits(ds.config, 10 * 2**20, "GPU memory", count=1, itemsize=4)


def test_check_mjx_refuses_by_name_with_the_reason():
    model = mujoco.MjModel.from_xml_string(PILE_XML)
    observations = observe.parse(model, ("qpos", "M", "ncon", "geom_xquat", "qfrc_spring",
                                         "nefc", "xmat"))
    with pytest.raises(ValueError) as info:
        mjx_observe.check(observations, mjx.make_data(model, impl="jax"))
    message = str(info.value)
    assert message.startswith("record: backend='mjx' cannot record M: MJX stores M "
                              "with shape (")
    assert ("ncon: MJX holds ncon as a constant of the compiled model (a size "
            "fixed at compilation), not per trajectory") in message
    assert "nefc: MJX holds nefc as a constant" in message
    assert "xmat:" not in message  # (n, 3, 3) in MJX: the same values, reshaped
    assert "geom_xquat: MJX has no field geom_xquat" in message
    assert "qfrc_spring: MJX has no field qfrc_spring" in message
    assert "qpos:" not in message
    assert message.endswith("use backend='cpu' for these")


def test_what_mjx_cannot_record_is_refused_at_construction(rich_model):
    import simloader
    with pytest.raises(ValueError, match="record: backend='mjx' cannot record M: "):
        simloader.SimDataset(rich_model, backend="mjx", nbatch=2, nstep=4, record=("M",))


@pytest.mark.parametrize("record_every", [1, 5])
def test_mjx_records_what_the_rollout_backend_records(record_every, cache_dir):
    import simloader
    from test_mjx import CONTACT_FREE_TOL
    control = np.random.default_rng(0).uniform(-1, 1, (3, 20, 1))
    kwargs = dict(nbatch=3, nstep=20, control=control, num_batches=2, continue_episodes=True,
                  record=("qpos", "xpos", "sensor:pole_angle", "qvel"),
                  record_every=record_every)
    mjx_batches = list(simloader.SimDataset("cartpole", backend="mjx",
                                            compilation_cache=cache_dir, **kwargs))
    c_batches = list(simloader.SimDataset("cartpole", backend="cpu", **kwargs))
    for got, want in zip(mjx_batches, c_batches, strict=True):
        assert set(got) == set(want)
        for key in kwargs["record"]:
            assert got[key].shape == want[key].shape == (3, 20 // record_every,
                                                          *want[key].shape[2:])
            assert got[key].dtype == torch.float32
            np.testing.assert_allclose(got[key].numpy(), want[key].numpy(),
                                       atol=CONTACT_FREE_TOL, err_msg=key)
        assert got.view("qpos", "hinge").shape == (3, 20 // record_every, 1)
