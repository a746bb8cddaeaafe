"""Domain randomization on the rollout backend: parity, statistics, errors, variants."""

import copy
import re

import mujoco
import numpy as np
import pytest
from mujoco import rollout

import simloader
from simloader import controls
from simloader import randomize as dr

SPEC = [
    dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole"),
    dr.add("dof_damping", dr.LogUniform(1e-3, 1.0), on="hinge"),
    dr.set("actuator_gainprm", dr.Normal(10.0, 2.0, low=5.0, high=15.0), on="push", index=0),
    dr.scale("opt.gravity", dr.Uniform(0.8, 1.2), index=2),
]


def pole_variant(spec, rng):
    """A pole of another length, whose hinge reads `ref` when upright: variants differ in
    qpos0, so each must start from its own default state."""
    length = rng.uniform(0.5, 1.5)
    spec.geom("pole").fromto = [0, 0, 0, 0, 0, length]
    spec.site("tip").pos = [0, 0, length]
    spec.joint("hinge").ref = rng.uniform(-0.5, 0.5)
    return spec


def make(nbatch=64, nstep=20, randomize=SPEC, **kwargs):
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=nbatch, nstep=nstep,
                                control=controls.Uniform(), randomize=randomize, nthread=2,
                                **kwargs)


def equivalent_models(model, params):
    """The list of models `mujoco.rollout` needs to run what the dataset ran."""
    out = []
    for i in range(len(next(iter(params.values())))):
        m = copy.copy(model)
        m.body("pole").mass[0] = params["body_mass[pole]"][i, 0]
        m.dof_damping[m.jnt_dofadr[m.joint("hinge").id]] = params["dof_damping[hinge]"][i, 0]
        m.actuator("push").gainprm[0] = params["actuator_gainprm[push]"][i, 0]
        m.opt.gravity[2] = params["opt.gravity"][i, 0]
        mujoco.mj_setConst(m, mujoco.MjData(m))
        out.append(m)
    return out


def test_equals_mujoco_rollout_on_the_equivalent_models():
    ds = make(nbatch=8, nstep=40)
    batch = next(iter(ds))
    params = {k: v.numpy() for k, v in batch["params"].items()}
    models = equivalent_models(ds.model, params)
    state, sensordata = rollout.rollout(models, [mujoco.MjData(ds.model) for _ in range(2)],
                                        batch["initial_state"].numpy(), batch["control"].numpy())
    np.testing.assert_array_equal(batch["state"].numpy(), state)
    np.testing.assert_array_equal(batch["sensordata"].numpy(), sensordata)


def test_values_in_range_spread_as_declared_and_distinct():
    params = {k: v.numpy()[:, 0] for k, v in next(iter(make(nbatch=2000, nstep=1)))["params"].items()}
    base = simloader.load_model("cartpole")
    mass = params["body_mass[pole]"] / base.body("pole").mass[0]
    assert mass.min() >= 0.5 and mass.max() <= 2.0
    assert abs(mass.mean() - 1.25) < 0.03 and abs(mass.std() - 1.5 / np.sqrt(12)) < 0.03
    damping = params["dof_damping[hinge]"] - base.dof_damping[1]
    assert damping.min() >= 1e-3 and damping.max() <= 1.0
    # log-uniform: the log is uniform, mean log(1e-3)/2, standard error 0.045 here
    assert abs(np.log(damping).mean() - np.log(np.sqrt(1e-3))) < 0.2
    gain = params["actuator_gainprm[push]"]
    assert gain.min() >= 5 and gain.max() <= 15 and abs(gain.mean() - 10) < 0.15
    assert len(np.unique(mass)) == 2000


def test_fresh_per_batch_and_once_per_episode():
    a, b = list(make(nbatch=4, num_batches=2))
    assert not np.array_equal(a["params"]["body_mass[pole]"], b["params"]["body_mass[pole]"])
    a, b = list(make(nbatch=4, num_batches=2, continue_episodes=True))
    for key in a["params"]:
        np.testing.assert_array_equal(a["params"][key], b["params"][key])


def test_only_the_randomized_fields_vary():
    ds = make(nbatch=3, randomize=[dr.add("dof_damping", dr.Uniform(0.1, 0.2), on="hinge")])
    backend = ds.make_backend()
    try:
        backend.produce(0)
        base = ds.model
        for sim in range(3):
            m = backend.batch.get_model(sim)
            for name in dir(base):
                value = getattr(base, name, None)
                if isinstance(value, np.ndarray) and value.dtype.kind == "f" and name != "dof_damping":
                    np.testing.assert_array_equal(getattr(m, name), value, err_msg=name)
            assert m.dof_damping[1] != base.dof_damping[1]
            assert m.dof_damping[0] == base.dof_damping[0]
    finally:
        backend.close()


@pytest.mark.parametrize("param,message", [
    (dr.scale("body_masses", dr.Uniform(1, 2)),
     "randomize: 'body_masses' is not a floating-point MjModel field or opt.* option "
     "(did you mean 'body_mass'"),
    (dr.scale("body_mass", dr.Uniform(1, 2), on="pol"),
     "randomize: body_mass: no body named 'pol' (did you mean 'pole'"),
    (dr.set("geom_friction", dr.Uniform(0.3, 1.2), on="ground", index=0),
     "randomize: geom_friction: no geom named 'ground'; its geoms are ['floor', 'rail', 'cart', "
     "'pole']"),
    (dr.add("dof_damping", dr.Uniform(0.0, 1.0), on="pole"),
     "randomize: dof_damping: no joint named 'pole'; its joints are ['slider', 'hinge']"),
    (dr.scale("body_mass", dr.Uniform(2, 1), on="pole"),
     "randomize: body_mass[pole]: Uniform expects finite low <= high, got low=2, high=1"),
    (dr.set("body_mass", dr.Normal(0.1, 0.1), on="pole"),
     "randomize: body_mass[pole]: the draw can make body_mass negative (lowest value -inf)"),
    (dr.add("body_mass", dr.Uniform(-1.0, 0.0), on="pole"),
     "randomize: body_mass[pole]: the draw can make body_mass negative"),
    (dr.scale("body_mass", dr.LogUniform(0.0, 1.0), on="pole"),
     "randomize: body_mass[pole]: LogUniform expects finite 0 < low <= high"),
    (dr.scale("opt.gravity", dr.Uniform(1, 2), on="cart"),
     "randomize: opt.gravity has no objects; leave on=None"),
    (dr.set("geom_friction", dr.Uniform(0.1, 1.0), on="cart", index=3),
     "randomize: geom_friction[cart]: index must be in [0, 3), got 3"),
])
def test_bad_parameters_fail_at_construction(param, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        make(randomize=[param])


def test_variants_pool_sampled_per_trajectory():
    def longer_pole(spec, rng):
        length = rng.uniform(0.5, 1.5)
        spec.geom("pole").fromto = [0, 0, 0, 0, 0, length]
        spec.site("tip").pos = [0, 0, length]
        return spec

    ds = make(nbatch=6, randomize=dr.Variants(longer_pole, count=4))
    batch = next(iter(ds))
    variant = batch["params"]["variant"].numpy()
    assert variant.min() >= 0 and variant.max() < 4
    pool = ds.config.variants
    assert len({m.geom("pole").size[1] for m in pool}) == 4
    state, _ = rollout.rollout([pool[i] for i in variant],
                               [mujoco.MjData(pool[0]) for _ in range(2)],
                               batch["initial_state"].numpy(), batch["control"].numpy())
    np.testing.assert_array_equal(batch["state"].numpy(), state)


def test_each_variant_starts_from_its_own_defaults():
    ds = make(nbatch=8, randomize=dr.Variants(pole_variant, count=4))
    batch = next(iter(ds))
    pool = [ds.config.variants[v] for v in batch["params"]["variant"].numpy()]
    assert len({m.qpos0[1] for m in pool}) > 1  # the variants' default states differ
    np.testing.assert_array_equal(batch["initial_state"].numpy(),
                                  simloader.initial.default_states(pool, None))
    state, _ = rollout.rollout(pool, [mujoco.MjData(pool[0]) for _ in range(2)],
                               batch["initial_state"].numpy(), batch["control"].numpy())
    np.testing.assert_array_equal(batch["state"].numpy(), state)


def test_variants_of_different_sizes_are_rejected():
    def extra_body(spec, rng):
        if rng.uniform() < 2:  # always
            spec.worldbody.add_body(name="extra").add_geom(size=[0.1, 0, 0])
        return spec

    def sometimes(spec, rng):
        return extra_body(spec, rng) if rng.uniform() < 0.5 else spec

    with pytest.raises(ValueError, match=r"randomize: variant\[\d+\]: models must have identical "
                                         r"sizes; nbody is"):
        make(randomize=dr.Variants(sometimes, count=8))
