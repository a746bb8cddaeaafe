"""The Warp engine (`backend="warp"`): float32 parity with MuJoCo C for every control_spec
component, overflow flags, buffer sizing, continuation, resume, randomization and its refusals.

Without a GPU these run MuJoCo Warp's CPU kernels for real (`SIMLOADER_WARP_ON_CPU=1`, set for
this module only): slow, so sizes are small. Warp compiles its kernels once per machine into
its cache (about a minute on a CPU for the first model). Tests marked `gpu` run the humanoid on
the GPU machine.
"""

import warnings

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

pytest.importorskip("mujoco.mjx")
pytest.importorskip("warp")

import simloader  # noqa: E402
from simloader import controls  # noqa: E402
from simloader import randomize as dr  # noqa: E402
from conftest import FAR_SITE_X0, FAR_SITE_XML, RICH_XML  # noqa: E402
from test_mjx import CONTACT_FREE_TOL, ONE_STEP_TOL  # noqa: E402
from test_randomize import pole_variant  # noqa: E402

S = mujoco.mjtState
EVERY_INPUT = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED | S.mjSTATE_XFRC_APPLIED
                  | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT | S.mjSTATE_EQ_ACTIVE)
HAS_GPU = torch.cuda.is_available()


# MuJoCo Warp on the CPU where no GPU is (conftest.warp_on_cpu)
pytestmark = pytest.mark.usefixtures("warp_on_cpu")


@pytest.fixture(scope="module")
def rich():
    return mujoco.MjModel.from_xml_string(RICH_XML)


def dataset(model, cache_dir, **kwargs):
    kwargs = {"backend": "warp", **kwargs}
    return simloader.SimDataset(model, **kwargs)


def c_rollout(model, batch, spec=int(S.mjSTATE_CTRL)):
    """MuJoCo C from the delivered float32 initial states and controls (as float64)."""
    x0 = batch["initial_state"].cpu().numpy().astype(np.float64)
    u = batch["control"].cpu().numpy().astype(np.float64)
    return rollout.rollout(model, mujoco.MjData(model), x0, u, control_spec=spec)


def test_contact_free_trajectories_match_mujoco_c(cache_dir):
    model = simloader.load_model("cartpole")
    ds = dataset(model, cache_dir, nbatch=4, nstep=60, control=controls.Uniform(),
                 num_batches=1)
    batch = next(iter(ds))
    assert batch["state"].dtype == torch.float32 and not batch["diverged"].any()
    built = ds.stats["compile_s"]  # the engine built once, its seconds counted
    assert built > 0
    next(iter(ds))  # a second iterator reuses the engine: nothing more is built
    assert ds.stats["compile_s"] == built
    state, sensordata = c_rollout(model, batch)
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)
    np.testing.assert_allclose(batch["sensordata"].cpu().numpy(), sensordata,
                               atol=CONTACT_FREE_TOL)
    assert ds.stats["backend"] == "warp"
    assert "backend='warp'" in ds.describe()


def test_every_control_spec_component_matches_mujoco_c_over_one_contact_step(rich, cache_dir):
    # the ball rests on the floor (contacts), the mocap target is welded when eq_active is 1
    control = {"ctrl": controls.Uniform(), "qfrc_applied": controls.Normal(std=1.0),
               "xfrc_applied": controls.Normal(std=3.0, on="ball"),
               "mocap_pos": controls.Normal(std=0.1), "mocap_quat": controls.Normal(std=0.1),
               "eq_active": controls.Constant(1.0)}
    ds = dataset(rich, cache_dir, nbatch=8, nstep=1, control_spec=EVERY_INPUT, control=control,
                 initial_state="raised", num_batches=1)
    batch = next(iter(ds))
    state, sensordata = c_rollout(rich, batch, EVERY_INPUT)
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=ONE_STEP_TOL)
    np.testing.assert_allclose(batch["sensordata"].cpu().numpy(), sensordata, atol=ONE_STEP_TOL)
    assert not batch["overflow"].any()


def test_default_buffers_hold_a_contact_rich_batch(rich, cache_dir):
    # balls dropped on the floor: contacts appear during the batch
    ds = dataset(rich, cache_dir, nbatch=16, nstep=100, control=controls.Uniform(),
                 num_batches=1)
    options = ds.config.options
    assert options.naconmax >= 16 * 2 and options.njmax >= 4
    batch = next(iter(ds))
    assert batch["overflow"].dtype == torch.bool and batch["overflow"].shape == (16,)
    assert not batch["overflow"].any() and ds.stats["overflow"] == 0
    assert f"naconmax={options.naconmax}" in ds.describe()


def test_overflow_is_flagged_per_trajectory_counted_and_said_once(rich, cache_dir):
    ds = dataset(rich, cache_dir, nbatch=4, nstep=60, naconmax=1, njmax=1, num_batches=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batches = list(ds)
    assert all(b["overflow"].all() for b in batches)
    assert ds.stats["overflow"] == 8
    said = [str(w.message) for w in caught if "MuJoCo Warp's buffer sizes" in str(w.message)]
    assert len(said) == 1, said
    assert "contacts exceeded naconmax=1 (the pool of the whole batch): pass a larger " \
           "naconmax=" in said[0]


def test_continued_chunks_concatenate_to_one_long_rollout(cache_dir):
    model = simloader.load_model("cartpole")
    ds = dataset(model, cache_dir, nbatch=3, nstep=20, continue_episodes=True, num_batches=2,
                 control=controls.Uniform())
    first, second = list(ds)
    np.testing.assert_array_equal(second["initial_state"].cpu().numpy(), first["state"][:, -1].cpu().numpy())
    c_state, _ = rollout.rollout(
        model, mujoco.MjData(model), first["initial_state"].cpu().numpy().astype(np.float64),
        np.concatenate([first["control"].cpu(), second["control"].cpu()], axis=1).astype(np.float64))
    got = np.concatenate([first["state"].cpu(), second["state"].cpu()], axis=1)
    np.testing.assert_allclose(got, c_state, atol=CONTACT_FREE_TOL)


def test_resume_continues_the_stream(cache_dir):
    model = simloader.load_model("cartpole")
    kwargs = dict(nbatch=3, nstep=10, continue_episodes=True, control=controls.Uniform(),
                  num_batches=3)
    ds = dataset(model, cache_dir, **kwargs)
    it = iter(ds)
    next(it)
    state = ds.state_dict()
    expected = [b["state"].clone() for b in it]
    resumed = dataset(model, cache_dir, **kwargs)
    resumed.load_state_dict(state)
    for want, got in zip(expected, resumed, strict=True):
        np.testing.assert_array_equal(got["state"].cpu().numpy(), want.cpu().numpy())


def test_randomized_parameters_match_mujoco_c_on_the_equivalent_models(cache_dir):
    model = simloader.load_model("cartpole")
    ds = dataset(model, cache_dir, nbatch=3, nstep=40, control=controls.Uniform(),
                 randomize=[dr.scale("dof_damping", dr.Uniform(50.0, 200.0))], num_batches=1)
    batch = next(iter(ds))
    damping = batch["params"]["dof_damping"].cpu().numpy()
    models = []
    for row in damping:
        m = simloader.load_model("cartpole")
        m.dof_damping[:] = row
        models.append(m)
    state, _ = rollout.rollout(models, mujoco.MjData(model),
                               batch["initial_state"].cpu().numpy().astype(np.float64),
                               batch["control"].cpu().numpy().astype(np.float64))
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)
    plain = next(iter(dataset(model, cache_dir, nbatch=3, nstep=40, control=controls.Uniform(),
                              num_batches=1)))
    assert np.abs(plain["state"].cpu().numpy() - batch["state"].cpu().numpy()).max() > 10 * CONTACT_FREE_TOL


def test_randomized_setconst_inputs_and_options_match_mujoco_c(cache_dir):
    # body masses feed what mj_setConst derives (MuJoCo Warp's set_const recomputes it per
    # trajectory); gravity is an option, held per trajectory as well
    model = simloader.load_model("cartpole")
    ds = dataset(model, cache_dir, nbatch=3, nstep=40, control=controls.Uniform(),
                 randomize=[dr.scale("body_mass", dr.Uniform(0.3, 3.0), on="pole"),
                            dr.scale("opt.gravity", dr.Uniform(0.5, 1.5), index=2)],
                 num_batches=1)
    batch = next(iter(ds))
    params = {k: v.cpu().numpy() for k, v in batch["params"].items()}
    models = []
    for i in range(3):
        m = simloader.load_model("cartpole")
        m.body_mass[m.body("pole").id] = params["body_mass[pole]"][i, 0]
        m.opt.gravity[2] = params["opt.gravity"][i, 0]
        mujoco.mj_setConst(m, mujoco.MjData(m))
        models.append(m)
    state, _ = rollout.rollout(models, mujoco.MjData(model),
                               batch["initial_state"].cpu().numpy().astype(np.float64),
                               batch["control"].cpu().numpy().astype(np.float64))
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)


def test_what_warp_cannot_randomize_is_refused_by_name(cache_dir):
    spec = dr.scale("dof_length", dr.Uniform(0.5, 2.0))
    with pytest.raises(ValueError) as info:
        dataset(simloader.load_model("cartpole"), cache_dir, nbatch=2, nstep=2,
                randomize=[spec])
    assert ("backend='warp' cannot randomize dof_length (MuJoCo Warp shares it across all "
            "trajectories of a batch)") in str(info.value)
    assert "dof_damping" in str(info.value)  # the list of what it can randomize


def test_auto_takes_the_cpu_where_warp_cannot_run_and_says_why(rich, cache_dir, monkeypatch):
    monkeypatch.delenv("SIMLOADER_WARP_ON_CPU")
    if HAS_GPU:
        pytest.skip("on a GPU, auto may take Warp for a model with contacts (test_gpu_*)")
    ds = simloader.SimDataset(rich, backend="auto", nbatch=2, nstep=2)
    assert ds.config.backend == "cpu"
    assert "chosen: auto: estimated steps/s" in ds.describe()
    assert "warp ~" not in ds.describe()  # not a candidate without a CUDA GPU
    with pytest.raises(ValueError, match="backend: 'warp' cannot run here: MuJoCo Warp needs a "
                                         "CUDA GPU, and torch sees none here"):
        simloader.SimDataset(rich, backend="warp", nbatch=2, nstep=2)


# --- on the GPU machine ------------------------------------------------------------------------

def humanoid():
    """The dm_control humanoid, built in (../shared/models/dm_control's, includes inlined)."""
    return simloader.load_model("humanoid")


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason="needs a CUDA GPU")
def test_gpu_humanoid_one_step_matches_mujoco_c_and_auto_takes_warp(cache_dir):
    model = humanoid()
    # auto takes Warp for a large batch of a model with contacts (auto_choice results)
    assert simloader.SimDataset(model, backend="auto", nbatch=8192, nstep=1).config.backend \
        == "warp"
    ds = simloader.SimDataset(model, backend="warp", nbatch=64, nstep=1,
                              control=controls.Uniform(), num_batches=1)
    batch = next(iter(ds))
    assert batch["state"].is_cuda
    state, sensordata = c_rollout(model, batch)
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=ONE_STEP_TOL)
    assert not batch["overflow"].any()


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason="needs a CUDA GPU")
def test_gpu_humanoid_batch_flags_overflow_and_keeps_the_rest(cache_dir):
    model = humanoid()
    ds = simloader.SimDataset(model, backend="warp", nbatch=256, nstep=100,
                              control=controls.Uniform(), naconmax=256, num_batches=1)
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        batch = next(iter(ds))
    assert batch["overflow"].any()
    assert ds.stats["overflow"] == int(batch["overflow"].sum())


def test_warmup_command_compiles_ahead_of_time(capsys):
    from simloader import cli
    cli.main(["warmup", "cartpole", "--backend", "warp", "--nbatch", "4", "--nstep", "5"])
    out = capsys.readouterr().out
    assert "backend='warp'" in out and "warm: compiled in" in out


def test_spawned_dataloader_worker_streams_the_same_batches(cache_dir):
    model = simloader.load_model("cartpole")
    kwargs = dict(nbatch=3, nstep=10, control=controls.Uniform(), num_batches=2)
    expected = [b["state"].cpu() for b in dataset(model, cache_dir, **kwargs)]
    loader = torch.utils.data.DataLoader(dataset(model, cache_dir, **kwargs), batch_size=None,
                                         num_workers=1, multiprocessing_context="spawn")
    got = [b["state"].cpu() for b in loader]
    assert len(got) == 2
    for want, have in zip(expected, got):
        np.testing.assert_array_equal(have.numpy(), want.numpy())


def test_a_model_list_runs_each_trajectory_on_its_model(cache_dir):
    models = []
    for damping in (0.0, 1.0, 4.0):  # explicit Euler: stable below ~6 (the pole is light)
        m = simloader.load_model("cartpole")
        m.dof_damping[:] = damping
        models.append(m)
    ds = dataset(models[0], cache_dir, nbatch=3, nstep=40, control=controls.Uniform(),
                 randomize=models, num_batches=1)
    batch = next(iter(ds))
    state, _ = rollout.rollout(models, mujoco.MjData(models[0]),
                               batch["initial_state"].cpu().numpy().astype(np.float64),
                               batch["control"].cpu().numpy().astype(np.float64))
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)


def damped_hinge(spec, rng):
    spec.joint("hinge").damping = [rng.uniform(0.0, 5.0), 0, 0]
    return spec


def test_variants_run_on_their_own_models(cache_dir):
    ds = dataset("cartpole", cache_dir, nbatch=4, nstep=30, control=controls.Uniform(),
                 randomize=dr.Variants(damped_hinge, count=3), num_batches=1)
    batch = next(iter(ds))
    pool = ds.config.variants
    models = [pool[i] for i in batch["params"]["variant"].cpu().numpy()]
    state, _ = rollout.rollout(models, mujoco.MjData(models[0]),
                               batch["initial_state"].cpu().numpy().astype(np.float64),
                               batch["control"].cpu().numpy().astype(np.float64))
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)


def heavier_pole(spec, rng):
    spec.geom("pole").mass = rng.uniform(0.05, 0.5)
    return spec


def test_variants_differing_in_derived_constants_run_on_their_own_models(cache_dir):
    # heavier poles: masses, inertias and what MuJoCo derives from them differ per variant
    ds = dataset("cartpole", cache_dir, nbatch=4, nstep=30, control=controls.Uniform(),
                 randomize=dr.Variants(heavier_pole, count=3), num_batches=1)
    batch = next(iter(ds))
    models = [ds.config.variants[i] for i in batch["params"]["variant"].cpu().numpy()]
    state, _ = rollout.rollout(models, mujoco.MjData(models[0]),
                               batch["initial_state"].cpu().numpy().astype(np.float64),
                               batch["control"].cpu().numpy().astype(np.float64))
    np.testing.assert_allclose(batch["state"].cpu().numpy(), state, atol=CONTACT_FREE_TOL)


def test_variants_differing_in_what_warp_shares_are_refused_by_name(cache_dir):
    with pytest.raises(ValueError, match=r"randomize: variant\[1\]: dof_length differs from "
                                         r"randomize: variant\[0\], but with backend='warp' it "
                                         r"cannot differ per trajectory \(MuJoCo Warp shares "
                                         r"it across all trajectories of a batch\)"):
        dataset("cartpole", cache_dir, nbatch=4, nstep=30,
                randomize=dr.Variants(pole_variant, count=3))


def test_recorded_fields_every_kth_step_match_the_rollout_backend(rich, cache_dir):
    # a contact step apart, float32 against float64: one frame of 2 steps from the keyframe
    control = np.random.default_rng(0).uniform(-1, 1, (4, 2, rich.nu))
    kwargs = dict(nbatch=4, nstep=2, control=control, initial_state="raised", num_batches=1,
                  record=("qpos", "xpos", "sensor:ball", "time"), record_every=2)
    got = next(iter(dataset(rich, cache_dir, **kwargs)))
    want = next(iter(simloader.SimDataset(rich, backend="cpu", **kwargs)))
    for key in kwargs["record"]:
        assert got[key].shape == want[key].shape == (4, 1, *want[key].shape[2:]), key
        np.testing.assert_allclose(got[key].cpu().numpy(), want[key].numpy(),
                                   atol=ONE_STEP_TOL, err_msg=key)


def test_a_bad_input_does_not_reach_later_steps(cache_dir):
    # each input gets a buffer of its own before a step; one made from the previous step's
    # (`u + 0 * old`) would carry a NaN force into every later step of that trajectory
    xfrc = int(S.mjSTATE_XFRC_APPLIED)
    control = np.random.default_rng(0).uniform(-1, 1, (2, 10, 6 * 3))
    control[0, 3] = np.nan
    batch = next(iter(dataset(simloader.load_model("cartpole"), cache_dir, nbatch=2, nstep=10,
                              control_spec=xfrc, control=control, num_batches=1)))
    assert batch["diverged"].tolist() == [True, False]
    time = batch["state"][0, :, 0].cpu().numpy()  # restarted at step 4, then runs on
    assert time[-1] > time[4] > 0 and np.isfinite(batch["state"].cpu().numpy()).all()


def test_a_diverged_trajectory_restarts_at_the_reset_state_and_runs_on(cache_dir):
    # the divergence check and restart run in the engine's own Warp kernel (`fused.py`): a
    # huge force at step 5 makes trajectory 1 unstable; it restarts as mj_resetData leaves it
    # (time 0, qpos0, zero velocity and sensors) and runs on from there with its next rows;
    # the others are untouched. Each part is MuJoCo C's within float32's tolerance
    model = simloader.load_model("cartpole")
    qfrc = int(S.mjSTATE_QFRC_APPLIED)
    control = np.random.default_rng(1).uniform(-1, 1, (3, 12, model.nv))
    control[1, 5] = 1e30
    batch = next(iter(dataset(model, cache_dir, nbatch=3, nstep=12, control_spec=qfrc,
                              control=control, num_batches=1)))
    assert batch["diverged"].tolist() == [False, True, False]
    state = batch["state"].cpu().numpy()
    want, _ = c_rollout(model, batch, spec=qfrc)
    np.testing.assert_allclose(state[[0, 2]], want[[0, 2]], atol=CONTACT_FREE_TOL)
    np.testing.assert_allclose(state[1, :5], want[1, :5], atol=CONTACT_FREE_TOL)
    reset = np.concatenate([[0.0], model.qpos0, np.zeros(model.nv + model.na)])
    np.testing.assert_array_equal(state[1, 5], reset.astype(np.float32))
    assert not batch["sensordata"][1, 5].any()
    after, _ = rollout.rollout(model, mujoco.MjData(model), reset[None], control[1:2, 6:],
                               control_spec=qfrc)
    np.testing.assert_allclose(state[1, 6:], after[0], atol=CONTACT_FREE_TOL)


def test_a_warp_dataset_never_imports_jax(fresh_python):
    """The Warp engine is MuJoCo Warp driven from torch: constructing, iterating and
    describing a Warp dataset (with a policy or open loop) starts no JAX."""
    script = """
import sys
import simloader
from simloader import controls
for closed in (False, True):
    drive = ({"policy": lambda o: o["state"][:, :1] * 0} if closed
             else {"control": controls.Uniform()})
    ds = simloader.SimDataset("cartpole", backend="warp", nbatch=2, nstep=3,
                              num_batches=1, **drive)
    assert ds.config.backend == "warp", ds.describe()
    batch = next(iter(ds))
    assert batch["state"].shape == (2, 3, 5)
print(sorted(m for m in sys.modules if m == "jax" or m.startswith(("jax.", "jaxlib"))))
"""
    (out,) = fresh_python(script, [((), {"SIMLOADER_WARP_ON_CPU": "1"})])
    assert out.strip().splitlines()[-1] == "[]"


def test_the_warp_engine_equals_mjx_jax_within_the_named_tolerances(rich, cache_dir):
    """The same controls and initial states on both GPU engines (here on the CPU): 60
    contact-free cart-pole steps within CONTACT_FREE_TOL, one contact step of the rich model
    (every input) within ONE_STEP_TOL (absolute; relative 3e-5)."""
    control = np.random.default_rng(1).uniform(-1, 1, (3, 60, 1))
    kwargs = dict(nbatch=3, nstep=60, control=control, num_batches=1,
                  initial_state=simloader.initial.Perturbed(), seed=4)
    warp = next(iter(simloader.SimDataset("cartpole", backend="warp", **kwargs)))
    jax_ = next(iter(simloader.SimDataset("cartpole", backend="mjx", compilation_cache=cache_dir,
                                          **kwargs)))
    assert torch.equal(warp["initial_state"].cpu(), jax_["initial_state"].cpu())
    np.testing.assert_allclose(warp["state"].cpu().numpy(), jax_["state"].cpu().numpy(),
                               atol=CONTACT_FREE_TOL)
    u = np.random.default_rng(2).uniform(-1, 1, (2, 1, mujoco.mj_stateSize(rich, EVERY_INPUT)))
    kwargs = dict(nbatch=2, nstep=1, control=u, control_spec=EVERY_INPUT,
                  initial_state="raised", num_batches=1)
    warp = next(iter(simloader.SimDataset(rich, backend="warp", **kwargs)))
    jax_ = next(iter(simloader.SimDataset(rich, backend="mjx", compilation_cache=cache_dir,
                                          **kwargs)))
    # (and float32's relative precision on the arm's velocities, about 50 rad/s here)
    np.testing.assert_allclose(warp["state"].cpu().numpy(), jax_["state"].cpu().numpy(),
                               atol=ONE_STEP_TOL, rtol=3e-5)


def test_an_engine_goes_away_with_its_dataset():
    """Engines are cached per configuration for every epoch of a dataset, and freed with it
    (an engine holds device buffers and graphs)."""
    import gc
    import weakref
    from simloader.backends.warp import backend
    ds = dataset("cartpole", None, nbatch=2, nstep=3, control=controls.Uniform(), num_batches=1)
    list(ds)
    list(ds)  # a second epoch: the same engine
    (engine,) = backend._ENGINES[ds.config].values()
    alive = weakref.ref(engine)
    del ds, engine
    gc.collect()
    assert alive() is None


def test_two_iterators_of_one_continuing_dataset_keep_their_own_trajectories():
    """Two iterators share the dataset's engine: each continues its own trajectories."""
    kwargs = dict(nbatch=2, nstep=4, control=controls.Uniform(), continue_episodes=True,
                  num_batches=3)
    alone = list(dataset("cartpole", None, **kwargs))
    ds = dataset("cartpole", None, **kwargs)
    a, b = iter(ds), iter(ds)
    first = [next(a), next(b), next(a), next(b)]
    for got, want in zip([first[0], first[2]], alone[:2]):
        assert torch.equal(got["state"], want["state"])
    assert torch.equal(first[2]["initial_state"], first[0]["state"][:, -1])


def test_a_dataset_checked_while_an_engine_queues_waits_for_warps_device(cache_dir):
    """Checking a Warp dataset scopes Warp's CPU device, which belongs to the process: it
    waits while an engine holds the device (`runtime.WARP_LOCK`), or that engine's kernels
    would go to the CPU (seen on an H200: a CPU kernel compiled mid-run)."""
    import threading
    import time

    from simloader.backends.warp import runtime
    start = time.perf_counter()
    dataset("cartpole", cache_dir, nbatch=2, nstep=2, seed=123)
    alone = time.perf_counter() - start
    done = []

    def check():
        dataset("cartpole", cache_dir, nbatch=2, nstep=2, seed=124)
        done.append(time.perf_counter())

    with runtime.WARP_LOCK:  # as an engine holds it while it queues
        checker = threading.Thread(target=check)
        checker.start()
        time.sleep(2 * alone + 1.0)
        released = time.perf_counter()
    checker.join(60)
    assert done and done[0] >= released, (alone, done, released)


def test_a_non_finite_recorded_field_is_flagged_while_the_physics_stays_finite(cache_dir):
    # a derived field (site_xpos) is not among what the divergence check restarts: only the
    # check of the delivered frames can flag it
    model = mujoco.MjModel.from_xml_string(FAR_SITE_XML.format(pos="2.6e38"))
    ds = dataset(model, cache_dir, nbatch=8, nstep=12, record_every=3,
                 record=("state", "site_xpos"), control=controls.Uniform(), num_batches=1,
                 seed=4, initial_state=FAR_SITE_X0)
    batch = next(iter(ds))
    state = batch["state"]
    assert torch.isfinite(state).all()
    assert (state[:, 0, 1].abs() > 0.5).any()  # turned poles kept turning: nothing restarted
    finite = torch.isfinite(batch["site_xpos"]).flatten(1).all(1)
    assert not finite.all(), "the site should overflow float32 on a turned pole"
    assert finite.any()
    assert torch.equal(batch["diverged"].cpu(), ~finite.cpu())
