"""Domain randomization on the MJX backend: JAX draws that follow the declared distributions,
derived constants against mj_setConst, float32 parity with MuJoCo C on the equivalent models,
structural variants, one compilation, refusals. Each configuration compiles once (seconds on
the CPU), so each is a module-scoped fixture shared by several tests, and both continue
episodes with one trajectory restarting in every batch: a restart is where values are drawn
(every batch for every trajectory without `continue_episodes`), and tests/test_mjx_resume.py
resumes the same configurations.
"""

import copy
import dataclasses
import re

import mujoco
import numpy as np
import pytest
import torch

mjx = pytest.importorskip("mujoco.mjx")
import jax  # noqa: E402  (after the skip: JAX comes with MJX)
import jax.numpy as jnp  # noqa: E402

import simloader  # noqa: E402
from simloader import controls, draws  # noqa: E402
from simloader import randomize as dr  # noqa: E402
from simloader.backends.mjx import randomize as mjx_randomize  # noqa: E402
from simloader.backends.mjx import setconst as mjx_setconst  # noqa: E402
from test_mjx import (RUNAWAY, CONTACT_FREE_TOL, WithRunaway, c_rollout, host,  # noqa: E402
                      traces)
from test_randomize import SPEC, equivalent_models, pole_variant  # noqa: E402

# mj_setConst's constants from float32 kinematics and a float32 Cholesky of M at qpos0,
# relative to MuJoCo's float64 (measured: 4e-6 on the humanoid)
SETCONST_RTOL = 1e-4


# --- the JAX draws follow the declared distributions (no simulation) ---

N = 20000


def jax_draw(dist, seed):
    """N values of `dist` drawn with JAX (as inside MJX's batch function), float32."""
    like = jnp.zeros((), jnp.float32)
    return np.asarray(dist.draw(draws.JaxDraws(jax.random.key(seed)), (N,), like))


@pytest.mark.parametrize("dist, mean, std, low, high", [
    (dr.Uniform(0.5, 2.0), 1.25, 1.5 / np.sqrt(12), 0.5, 2.0),
    (dr.Normal(10.0, 2.0, low=7.0, high=15.0), None, None, 7.0, 15.0),
    (dr.Normal(1.0, 0.5), 1.0, 0.5, -np.inf, np.inf),
])
def test_jax_draws_in_range_with_the_declared_moments(dist, mean, std, low, high):
    draw = jax_draw(dist, 0)
    assert draw.dtype == np.float32 and draw.min() >= low and draw.max() <= high
    inside = (draw > low) & (draw < high)  # a clipped Normal piles up at its bounds
    assert len(np.unique(draw[inside])) > 0.99 * inside.sum()  # distinct per trajectory
    # the NumPy draw, same law
    reference = dist.draw(draws.NumpyDraws(np.random.default_rng(0)), (N,), np.zeros(()))
    # means within 5 standard errors, spreads within 5%
    se = reference.std() / np.sqrt(N)
    assert abs(draw.mean() - reference.mean()) < 5 * np.sqrt(2) * se
    assert abs(draw.std() / reference.std() - 1) < 0.05
    if mean is not None:
        assert abs(draw.mean() - mean) < 5 * se and abs(draw.std() / std - 1) < 0.05
    fresh = jax_draw(dist, 1)
    assert not np.any((fresh == draw) & inside)  # another key (batch): fresh values


def test_jax_log_uniform_is_uniform_in_log_space():
    draw = jax_draw(dr.LogUniform(1e-3, 1.0), 0)
    assert draw.min() >= np.float32(1e-3) and draw.max() <= 1.0
    logs = np.log(draw)
    # uniform on [log 1e-3, 0]: mean log(1e-3)/2, std 6.91/sqrt(12), standard error 0.014
    assert abs(logs.mean() - np.log(1e-3) / 2) < 0.07
    assert abs(logs.std() / (-np.log(1e-3) / np.sqrt(12)) - 1) < 0.05


def test_plan_draws_one_stream_per_parameter_and_shares_when_asked(cartpole):
    plan = dr.RandomizationPlan(cartpole, [
        dr.scale("body_mass", dr.Uniform(0.5, 2.0), on=["cart", "pole"], shared=True),
        dr.add("dof_damping", dr.Uniform(0.0, 1.0)),
    ])
    values = plan.sample_jax(jax.random.key(3), 500, jnp.float32)
    mass = np.asarray(values["body_mass[cart,pole]"]) / cartpole.body_mass[1:3]
    np.testing.assert_allclose(mass[:, 0], mass[:, 1], rtol=1e-6)  # one draw for both
    damping = np.asarray(values["dof_damping"]) - cartpole.dof_damping.astype(np.float32)
    assert not np.allclose(damping[:, 0], damping[:, 1])  # one draw each
    assert 0.5 <= mass.min() and mass.max() <= 2.0 and len(np.unique(mass[:, 0])) == 500


# --- derived constants: in-graph set_const against mj_setConst ---

TENDONS_XML = """
<mujoco>
  <worldbody>
    <geom type="plane" size="2 2 .1"/>
    <body name="slider" pos="0 0 1">
      <joint name="x" type="slide" axis="1 0 0"/><joint name="y" type="slide" axis="0 1 0"/>
      <geom type="sphere" size=".1" mass="2"/>
    </body>
    <body name="free" pos="1 0 1"><freejoint/><geom type="box" size=".1 .2 .3"/></body>
    <body name="arm" pos="0 1 1">
      <joint name="ball" type="ball"/>
      <geom type="capsule" fromto="0 0 0 .3 0 0" size=".03"/>
      <site name="s1" pos=".1 0 .05"/>
      <body name="fore" pos=".3 0 0">
        <joint name="elbow" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 .3 0 0" size=".03"/>
        <site name="s2" pos=".2 0 .05"/>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="fixed"><joint joint="x" coef="1"/><joint joint="elbow" coef="-0.5"/></fixed>
    <spatial name="spatial"><site site="s1"/><site site="s2"/></spatial>
  </tendon>
  <actuator>
    <motor joint="x" gear="3"/>
    <muscle tendon="spatial"/>
    <motor tendon="fixed"/>
  </actuator>
</mujoco>
"""


@pytest.mark.parametrize("which", ["cartpole", "humanoid", "tendons"])
def test_derived_constants_match_mj_set_const(which, cartpole, humanoid_path):
    model = {"cartpole": lambda: copy.copy(cartpole),
             "humanoid": lambda: mujoco.MjModel.from_xml_path(str(humanoid_path)),
             "tendons": lambda: mujoco.MjModel.from_xml_string(TENDONS_XML)}[which]()
    if which == "tendons":  # free, ball, slide-only ("simple") bodies, tendons, a muscle
        assert set(model.jnt_type) == {0, 1, 2, 3} and 2 in model.body_simple
    rng = np.random.default_rng(0)
    model.body_mass[1:] *= rng.uniform(0.5, 2.0, model.nbody - 1)
    model.body_inertia[1:] *= rng.uniform(0.5, 2.0, (model.nbody - 1, 1))
    model.dof_armature[:] += rng.uniform(0.0, 0.1, model.nv)
    model.actuator_gear[:, 0] *= rng.uniform(0.5, 2.0, model.nu)
    # MJX given the edited inputs, but the derived constants of the unedited model
    mx = mjx.put_model(model, impl="jax")
    stale = {field: np.asarray(getattr(mx, field)) for field in mjx_setconst.OUTPUTS}
    derived = jax.jit(mjx_setconst.SetConst(model))(mx, mjx.make_data(model, impl="jax"))
    mujoco.mj_setConst(model, mujoco.MjData(model))
    assert sorted(derived) == sorted(mjx_setconst.OUTPUTS)
    for field, value in derived.items():
        expected = getattr(model, field)
        # relative, and relative to the field's scale where MuJoCo's value is 0
        np.testing.assert_allclose(value, expected, rtol=SETCONST_RTOL, err_msg=field,
                                   atol=SETCONST_RTOL * np.abs(expected).max(initial=0))
        if expected.size:  # the edits changed it: keeping the model's would fail
            assert not np.allclose(stale[field], expected, rtol=10 * SETCONST_RTOL), field


# --- a randomized cartpole (mass, damping, gain, gravity), continuing episodes, one runaway
#     trajectory that restarts (with fresh values) in every batch ---

@pytest.fixture(scope="module")
def cartpole():
    return simloader.load_model("cartpole")


def params_kwargs(cache_dir):
    return dict(nbatch=8, nstep=20, num_batches=3, seed=3, control=controls.Uniform(),
                randomize=SPEC, initial_state=WithRunaway(), continue_episodes=True,
                compilation_cache=cache_dir)


@pytest.fixture(scope="module")
def randomized(cache_dir):
    ds = simloader.SimDataset("cartpole", backend="mjx", **params_kwargs(cache_dir))
    with traces() as seen:
        epochs = [list(ds), list(ds)]
    return ds, epochs, len(seen)


def test_one_compilation_over_batches_and_epochs(randomized):
    ds, epochs, ntraces = randomized
    assert ntraces + ds.stats["programs_loaded"] == 1 and ds.stats["compiles"] == 1
    assert ds.stats["batches"] == 6
    # the same seed gives the same stream, draws included
    for a, b in zip(*epochs):
        for key in a["params"]:
            np.testing.assert_array_equal(host(a["params"][key]), host(b["params"][key]))


def test_params_as_the_rollout_backend_returns_them(randomized, cartpole):
    _, (batches, _), _ = randomized
    ref = simloader.SimDataset("cartpole", backend="cpu", nbatch=8, nstep=1, num_batches=1,
                               randomize=SPEC, nthread=1)
    expected = next(iter(ref))["params"]
    for batch in batches:
        params = batch["params"]
        assert list(params) == list(expected)  # same keys, in the spec's order
        for key, value in params.items():
            assert value.shape == expected[key].shape == (8, 1)
            assert value.dtype == torch.float32  # the backend's native precision
        mass = host(params["body_mass[pole]"])[:, 0] / cartpole.body("pole").mass[0]
        assert mass.min() >= 0.5 - 1e-6 and mass.max() <= 2.0 + 1e-6
        assert len(np.unique(mass)) == 8  # distinct per trajectory
        gain = host(params["actuator_gainprm[push]"])
        assert gain.min() >= 5.0 and gain.max() <= 15.0


def test_values_last_an_episode_and_a_restart_draws_fresh_ones(randomized):
    _, (batches, _), _ = randomized
    ok = np.arange(8) != RUNAWAY
    for prev, nxt in zip(batches, batches[1:]):
        np.testing.assert_array_equal(host(nxt["diverged"]), ~ok)
        for key in prev["params"]:
            before, after = host(prev["params"][key]), host(nxt["params"][key])
            np.testing.assert_array_equal(after[ok], before[ok])
            assert np.all(after[RUNAWAY] != before[RUNAWAY]), key  # a new batch's draw


def test_chunks_match_mujoco_on_the_equivalent_models(randomized, cartpole):
    _, (batches, _), _ = randomized
    ok = np.flatnonzero(np.arange(8) != RUNAWAY)
    params = {k: host(v)[ok].astype(np.float64) for k, v in batches[0]["params"].items()}
    control = np.concatenate([host(b["control"]) for b in batches], axis=1)[ok]
    x0 = host(batches[0]["initial_state"])[ok]
    state, sensordata = c_rollout(equivalent_models(cartpole, params), x0, control)
    np.testing.assert_allclose(np.concatenate([host(b["state"])[ok] for b in batches], 1), state,
                               rtol=0, atol=CONTACT_FREE_TOL)
    np.testing.assert_allclose(np.concatenate([host(b["sensordata"])[ok] for b in batches], 1),
                               sensordata, rtol=0, atol=CONTACT_FREE_TOL)
    # the parameters matter: the unrandomized model is far from it
    base, _ = c_rollout(cartpole, x0, control)
    assert np.abs(base - state).max(axis=(1, 2)).min() > 10 * CONTACT_FREE_TOL


def test_only_the_randomized_and_derived_fields_are_batched(randomized):
    ds, _, _ = randomized
    from simloader.backends.mjx import backend as mjx_backend
    program, = mjx_backend._PROGRAMS[ds.config].values()
    batched = {jax.tree_util.keystr(path) for path, axis in
               jax.tree_util.tree_flatten_with_path(program.randomizer.axes)[0] if axis == 0}
    assert batched == {".body_mass", ".dof_damping", ".actuator_gainprm", ".opt.gravity"} | {
        f".{f}" for f in mjx_setconst.OUTPUTS}


# --- structural variants, continuing, one trajectory diverging in every batch ---

DIVERGING = 2


def variant_kwargs(cache_dir):
    """Four variants, continuing episodes, controls fixed but NaN in one trajectory."""
    control = np.random.default_rng(0).uniform(-1, 1, (4, 20, 1))
    control[DIVERGING, 5] = np.nan
    return dict(nbatch=4, nstep=20, num_batches=3, control=control, seed=5,
                randomize=dr.Variants(pole_variant, count=4), continue_episodes=True,
                compilation_cache=cache_dir)


@pytest.fixture(scope="module")
def variants(cache_dir):
    ds = simloader.SimDataset("cartpole", backend="mjx", **variant_kwargs(cache_dir))
    return ds, list(ds)


def test_variants_drawn_as_on_the_rollout_backend_once_per_episode(variants, cache_dir):
    ds, batches = variants
    kwargs = variant_kwargs(cache_dir)
    del kwargs["compilation_cache"]
    reference = next(iter(simloader.SimDataset("cartpole", backend="cpu", **kwargs)))
    first = host(batches[0]["params"]["variant"])
    np.testing.assert_array_equal(first, reference["params"]["variant"].numpy())
    assert batches[0]["params"]["variant"].dtype == reference["params"]["variant"].dtype
    # the same initial states: each variant's own defaults on both backends
    np.testing.assert_array_equal(host(batches[0]["initial_state"]),
                                  reference["initial_state"].numpy().astype(np.float32))
    ok = np.arange(4) != DIVERGING
    for index, batch in enumerate(batches):
        variant = host(batch["params"]["variant"])
        np.testing.assert_array_equal(variant[ok], first[ok])  # kept while the episode lasts
        # the diverged trajectory restarts with a fresh draw, the rollout backend's
        seed = np.random.SeedSequence(5, spawn_key=(0, index, simloader.seeds.RANDOMIZE))
        assert variant[DIVERGING] == dr.draw_variants(seed, 4, 4)[DIVERGING]
        np.testing.assert_array_equal(host(batch["diverged"]), ~ok)
    assert ds.stats["compiles"] == 1


def test_each_variant_starts_from_its_own_defaults(variants):
    ds, batches = variants
    pool = ds.config.variants
    assert len({m.qpos0[1] for m in pool}) == 4
    for batch in batches[1:]:  # only the diverged trajectory started afresh
        v = host(batch["params"]["variant"])[DIVERGING]
        np.testing.assert_array_equal(host(batch["initial_state"])[DIVERGING],
                                      simloader.initial.keyframe_state(pool[v], None).astype(
                                          np.float32))
    variant = host(batches[0]["params"]["variant"])
    np.testing.assert_array_equal(host(batches[0]["initial_state"])[:, 2],
                                  np.float32([pool[v].qpos0[1] for v in variant]))


def test_variant_chunks_match_mujoco_on_each_variant(variants):
    ds, batches = variants
    ok = np.flatnonzero(np.arange(4) != DIVERGING)
    variant = host(batches[0]["params"]["variant"])
    control = np.concatenate([host(b["control"]) for b in batches], axis=1)
    state, _ = c_rollout([ds.config.variants[v] for v in variant[ok]],
                         host(batches[0]["initial_state"])[ok], control[ok])
    got = np.concatenate([host(b["state"])[ok] for b in batches], axis=1)
    np.testing.assert_allclose(got, state, rtol=0, atol=CONTACT_FREE_TOL)
    # the variants matter: trajectories on the first variant would be far from it
    first, _ = c_rollout(ds.config.variants[0], host(batches[0]["initial_state"])[ok],
                         control[ok])
    differs = variant[ok] != 0
    assert differs.any() and np.abs(first - state).max(axis=(1, 2))[differs].min() > \
        10 * CONTACT_FREE_TOL


# --- refusals, at construction (no compilation) ---

def allowed():
    return ", ".join(mjx_randomize.FIELDS)


@pytest.mark.parametrize("param, message", [
    (dr.scale("geom_size", dr.Uniform(0.5, 2.0), on="pole"),
     "randomize: geom_size[pole]: backend='mjx' cannot randomize geom_size (MuJoCo derives "
     "constants from it that the MJX backend does not recompute); it can randomize "
     "{allowed} (backend='cpu' randomizes any floating-point field)"),
    (dr.scale("dof_invweight0", dr.Uniform(0.5, 2.0)),
     "randomize: dof_invweight0: backend='mjx' cannot randomize dof_invweight0 (MuJoCo derives "
     "it from other fields); it can randomize {allowed}"),
    (dr.scale("geom_fluid", dr.Uniform(0.5, 2.0), on="pole", index=0),
     "randomize: geom_fluid[pole]: backend='mjx' cannot randomize geom_fluid (MJX compiles it "
     "into the simulation)"),
    (dr.set("dof_frictionloss", dr.Uniform(0.0, 1.0), on="hinge"),
     "randomize: dof_frictionloss[hinge]: backend='mjx' randomizes dof_frictionloss only where "
     "the model's value is > 0 (MJX decides when the model is loaded which constraints have "
     "friction loss); give the model a positive dof_frictionloss there, or use "
     "backend='cpu'"),
    (dr.set("opt.viscosity", dr.Uniform(0.0, 1.0)),
     "randomize: opt.viscosity: backend='mjx' randomizes opt.viscosity only in a model with "
     "fluid forces (MJX turns them off when the model's density, viscosity and wind are all "
     "0); give the model a nonzero value, or use backend='cpu'"),
])
def test_fields_mjx_cannot_randomize_are_refused_with_the_list(param, message):
    with pytest.raises(ValueError, match=re.escape(message.format(allowed=allowed()))):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2, randomize=[param])


def euler_variant(spec, rng):
    """A variant that changes what MJX compiles in (the integrator), for every other one."""
    if rng.uniform() < 0.5:
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
    return spec


def extra_body(spec, rng):
    """A variant with another size (a body more), for every other one."""
    if rng.uniform() < 0.5:
        spec.worldbody.add_body(name="extra").add_geom(size=[0.1, 0, 0])
    return spec


@pytest.mark.parametrize("variant, message", [
    (euler_variant, r"randomize: variant\[\d+\]: model\.opt\.integrator differs from "
                    r"randomize: variant\[0\], but MJX compiles it into the simulation; only "
                    r"numeric parameters may differ across the models"),
    (extra_body, r"randomize: variant\[\d+\]: models must have identical sizes; nbody is"),
])
def test_variants_mjx_cannot_stack_are_refused(variant, message):
    with pytest.raises(ValueError, match=message):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2,
                             randomize=dr.Variants(variant, count=8))


def test_every_listed_field_is_a_traced_mjx_field_without_hidden_derived_constants(cartpole):
    mx = mjx.put_model(cartpole, impl="jax")
    names = {f.name for f in dataclasses.fields(mx)}
    for field in mjx_randomize.FIELDS:
        value = getattr(mx.opt, field[4:]) if field.startswith("opt.") else getattr(mx, field)
        assert isinstance(value, jax.Array), field  # a leaf: batched, not compiled in
        if not field.startswith("opt."):
            assert field in names and getattr(cartpole, field).size == value.size, field
        derives = field in mujoco.MjModel._setconst_inputs
        assert not derives or field in mjx_setconst.INPUTS or field.startswith("tendon_"), field
