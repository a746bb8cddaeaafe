"""The MJX backend: float32 parity with MuJoCo C and the rollout backend, divergence flags,
continuation, model lists, zero-copy hand-off, one compilation per configuration, workers, bad
input (reliability checks 2, 4, 7, 9, 11, 12). Compiling is slow on CPU (seconds per
configuration), so each configuration is a module-scoped fixture shared by several tests.
"""

import contextlib
import multiprocessing
import os
import subprocess
import sys
import textwrap

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

mjx = pytest.importorskip("mujoco.mjx")
import jax  # noqa: E402  (after the skip: JAX comes with MJX)

import simloader  # noqa: E402
from simloader import controls  # noqa: E402
from simloader.backends.mjx import pool as mjx_pool  # noqa: E402

# float32 MJX against float64 MuJoCo C
CONTACT_FREE_TOL = 2e-3  # a contact-free trajectory of NSTEP steps, absolute
ONE_STEP_TOL = 1e-4  # one step of a contact model, state, absolute
# its sensors also carry the float32 constraint solver's error in contact forces (2e-4 relative
# on the humanoid's ankle torques)
ONE_STEP_SENSOR_RTOL = 1e-3
NSTEP = 60

S = mujoco.mjtState
CTRL_XFRC = int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED)
FULLPHYSICS = int(S.mjSTATE_FULLPHYSICS)
KEYS = ("state", "sensordata", "control", "initial_state", "diverged")
TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"


@contextlib.contextmanager
def traces(fun_name="simulate"):
    """Collects one entry per JAX trace of the named function (the backend's batch function)."""
    seen = []

    def listener(event, duration, **kwargs):
        if event == TRACE_EVENT and kwargs.get("fun_name") == fun_name:
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def host(tensor):
    return tensor.cpu().numpy()


def c_rollout(models, x0, control=None, spec=int(S.mjSTATE_CTRL), nstep=None):
    """MuJoCo C from the delivered float32 initial states (as float64), warmstart zero."""
    model = models if isinstance(models, mujoco.MjModel) else models[0]
    return rollout.rollout(models, mujoco.MjData(model), np.asarray(x0, np.float64),
                           None if control is None else np.asarray(control, np.float64),
                           control_spec=spec, nstep=nstep)


@pytest.fixture(scope="module")
def cartpole():
    return simloader.load_model("cartpole")


# --- a contact-free model with controls and forces, and one trajectory given a NaN control ---

FAULTY, FAULT_STEP = 3, 20


def faulty_kwargs(model, cache_dir):
    """Cartpole, CTRL|XFRC_APPLIED from a fixed array: a push on the cart, a random wrench on
    the pole, and a NaN control in trajectory FAULTY at step FAULT_STEP."""
    nbatch = 5
    rng = np.random.default_rng(0)
    u = np.zeros((nbatch, NSTEP, mujoco.mj_stateSize(model, CTRL_XFRC)))
    u[..., 0] = rng.uniform(-1, 1, (nbatch, NSTEP))
    pole = 1 + 6 * model.body("pole").id
    u[..., pole:pole + 6] = rng.normal(scale=0.5, size=(nbatch, NSTEP, 6))
    u[FAULTY, FAULT_STEP, 0] = np.nan
    return dict(nbatch=nbatch, nstep=NSTEP, control=u, control_spec=CTRL_XFRC, num_batches=4,
                initial_state=simloader.initial.Perturbed(qpos_std=0.2, qvel_std=0.2), seed=7,
                prefetch=2, compilation_cache=cache_dir)


@pytest.fixture(scope="module")
def faulty(cartpole, cache_dir):
    kwargs = faulty_kwargs(cartpole, cache_dir)
    ds = simloader.SimDataset(cartpole, backend="mjx", **kwargs)
    with traces() as first_pass:
        batches = list(ds)
    return ds, batches, len(first_pass)


@pytest.fixture(scope="module")
def faulty_rollout(cartpole, cache_dir):
    kwargs = faulty_kwargs(cartpole, cache_dir)
    del kwargs["compilation_cache"]
    return list(simloader.SimDataset(cartpole, backend="cpu", nthread=2, **kwargs))


def test_matches_rollout_backend_with_ctrl_and_xfrc(faulty, faulty_rollout):
    _, batches, _ = faulty
    ok = np.arange(5) != FAULTY  # (before its fault, see below)
    for mine, ref in zip(batches, faulty_rollout):
        # same draws (float32-rounded): the same initial states and controls
        np.testing.assert_array_equal(host(mine["initial_state"]),
                                      ref["initial_state"].numpy().astype(np.float32))
        np.testing.assert_array_equal(host(mine["control"]),
                                      ref["control"].numpy().astype(np.float32))
        for key in ("state", "sensordata"):
            np.testing.assert_allclose(host(mine[key])[ok], ref[key].numpy()[ok], rtol=0,
                                       atol=CONTACT_FREE_TOL, err_msg=key)
        # the model moved: not a trivially equal pair of constant arrays
        assert np.abs(np.diff(ref["state"].numpy()[ok][..., 1:3], axis=1)).max() > 1e-3


def test_diverged_flags_exactly_the_faulty_trajectory(cartpole, faulty, faulty_rollout):
    ds, batches, _ = faulty
    expected = np.arange(5) == FAULTY
    reset = simloader.initial.keyframe_state(cartpole, None)  # what mj_resetData leaves
    for batch, ref in zip(batches, faulty_rollout):
        np.testing.assert_array_equal(host(batch["diverged"]), expected)
        np.testing.assert_array_equal(ref["diverged"].numpy(), expected)  # MuJoCo agrees
        # as MuJoCo, the faulty trajectory restarts from mj_resetData's state: no NaN delivered
        assert np.isfinite(host(batch["state"])).all()
        assert np.isfinite(host(batch["sensordata"])).all()
        np.testing.assert_array_equal(host(batch["state"])[FAULTY, FAULT_STEP], reset)
        np.testing.assert_allclose(host(batch["state"])[FAULTY, :FAULT_STEP],
                                   ref["state"].numpy()[FAULTY, :FAULT_STEP], rtol=0,
                                   atol=CONTACT_FREE_TOL)
    assert ds.stats["diverged"] == len(batches)


def test_same_batch_schema_as_rollout_backend(faulty, faulty_rollout):
    mine, ref = faulty[1][0], faulty_rollout[0]
    assert sorted(mine) == sorted(ref) == sorted(KEYS + simloader.streams.KEYS)
    for key in KEYS + simloader.streams.KEYS:
        assert mine[key].shape == ref[key].shape, key
    for key in KEYS:
        native = (torch.bool,) * 2 if key == "diverged" else (torch.float32, torch.float64)
        assert (mine[key].dtype, ref[key].dtype) == native, key


def test_compiles_once_per_configuration(faulty):
    ds, batches, first_pass = faulty
    # one trace for all four batches (none if an earlier test stored this program)
    assert len(batches) == 4 and first_pass + ds.stats["programs_loaded"] == 1
    compile_s = ds.stats["compile_s"]
    assert compile_s > 0
    with traces() as again:
        assert len(list(ds)) == 4  # a new iterator (an epoch) reuses the compiled function
    assert again == [] and ds.stats["compile_s"] == compile_s
    assert ds.stats["batches"] == 8 and ds.stats["steps"] == 8 * 5 * NSTEP


def test_zero_copy_and_kept_tensors_unchanged(faulty):
    ds, _, _ = faulty
    backend = ds.make_backend()
    produced = backend.produce(0)
    batch = backend.deliver(produced)
    device = produced.outputs["state"].device
    expected = torch.device("cuda", device.id) if device.platform == "gpu" else torch.device("cpu")
    for key in KEYS:
        assert batch[key].data_ptr() == produced.outputs[key].unsafe_buffer_pointer(), key
        assert batch[key].device == expected, key
    kept = {k: v.clone() for k, v in batch.items()}
    later = [backend.deliver(backend.produce(i)) for i in range(1, 4)]
    for key in KEYS:
        torch.testing.assert_close(batch[key], kept[key], rtol=0, atol=0, equal_nan=True)
        # every batch has its own buffers
        assert all(b[key].data_ptr() != batch[key].data_ptr() for b in later), key
    backend.close()


# --- continuation over a model list, with generated controls and a runaway trajectory ---

RUNAWAY = 2


class WithRunaway(simloader.initial.InitialStateGenerator):
    """Perturbed states, except trajectory RUNAWAY, which starts at an absurd velocity."""

    def sample(self, model, rng, nbatch):
        x = simloader.initial.Perturbed().sample(model, rng, nbatch)
        x[RUNAWAY, 1 + model.nq] = 1e12
        return x


@pytest.fixture(scope="module")
def pole_masses():
    return pole_mass_models()


def pole_mass_models():
    spec = mujoco.MjSpec.from_file(str(simloader.builtin_path("cartpole")))
    models = []
    for mass in (0.1, 0.2, 0.3):
        spec.body("pole").first_geom().mass = mass
        models.append(spec.compile())
    return models


def continued_kwargs(pole_masses, cache_dir):
    """A model list, continuing episodes, generated forces, one runaway trajectory."""
    return dict(nbatch=3, nstep=20, num_batches=3, randomize=pole_masses,
                continue_episodes=True, initial_state=WithRunaway(), control_spec=CTRL_XFRC,
                control={"xfrc_applied": controls.Normal(std=1.0, on="pole")},
                compilation_cache=cache_dir)


@pytest.fixture(scope="module")
def continued(pole_masses, cache_dir):
    ds = simloader.SimDataset(pole_masses[0], backend="mjx",
                              **continued_kwargs(pole_masses, cache_dir))
    return ds, list(ds)


def test_continued_chunks_concatenate_to_one_rollout_of_each_model(pole_masses, continued):
    _, batches = continued
    ok = [0, 1]
    for prev, nxt in zip(batches, batches[1:]):
        # exactly where the previous chunk ended
        np.testing.assert_array_equal(host(nxt["initial_state"])[ok], host(prev["state"])[ok, -1])
    control = np.concatenate([host(b["control"]) for b in batches], axis=1)
    state, sensordata = c_rollout(pole_masses[:2], host(batches[0]["initial_state"])[ok],
                                  control[ok], CTRL_XFRC)
    np.testing.assert_allclose(np.concatenate([host(b["state"])[ok] for b in batches], 1), state,
                               rtol=0, atol=CONTACT_FREE_TOL)
    np.testing.assert_allclose(np.concatenate([host(b["sensordata"])[ok] for b in batches], 1),
                               sensordata, rtol=0, atol=CONTACT_FREE_TOL)
    # trajectory 1 ran on its own (heavier) pole, not on the first model's
    light, _ = c_rollout(pole_masses[0], host(batches[0]["initial_state"])[[1]], control[[1]],
                         CTRL_XFRC)
    assert np.abs(state[1] - light[0]).max() > 10 * CONTACT_FREE_TOL


def test_generated_controls_drive_only_their_columns(pole_masses, continued):
    _, batches = continued
    control = host(batches[0]["control"])[..., 1:].reshape(3, 20, pole_masses[0].nbody, 6)
    pole = pole_masses[0].body("pole").id
    assert np.all(host(batches[0]["control"])[..., 0] == 0)  # undriven ctrl: mj_resetData's 0
    assert np.all(control[:, :, pole] != 0)
    assert np.all(np.delete(control, pole, axis=2) == 0)
    assert not np.array_equal(host(batches[0]["control"]), host(batches[1]["control"]))


def test_diverged_trajectory_restarts_from_a_fresh_initial_state(continued):
    ds, batches = continued
    for prev, nxt in zip(batches, batches[1:]):
        assert host(nxt["initial_state"])[RUNAWAY, 1 + ds.model.nq] == np.float32(1e12)
        assert not np.array_equal(host(nxt["initial_state"])[RUNAWAY],
                                  host(prev["state"])[RUNAWAY, -1])
    for batch in batches:
        np.testing.assert_array_equal(host(batch["diverged"]), np.arange(3) == RUNAWAY)


def test_model_list_batches_only_the_fields_that_differ(pole_masses, continued):
    ds, _ = continued
    _, axes = mjx_pool.put_models(ds.config, jax.devices()[0])
    batched = {jax.tree_util.keystr(path) for path, axis in
               jax.tree_util.tree_flatten_with_path(axes)[0] if axis == 0}
    assert {".body_mass", ".body_inertia"} <= batched
    assert ".geom_size" not in batched and ".opt.timestep" not in batched


# --- a contact model, one step against MuJoCo C ---

def test_one_step_of_contact_model_matches_mujoco(humanoid_path, cache_dir):
    model = mujoco.MjModel.from_xml_path(str(humanoid_path))
    data = mujoco.MjData(model)
    while data.time < 1.5:  # fallen over, lying on the floor
        mujoco.mj_step(model, data)
    x0 = np.empty(mujoco.mj_stateSize(model, FULLPHYSICS))
    mujoco.mj_getState(model, data, x0, FULLPHYSICS)
    ds = simloader.SimDataset(model, backend="mjx", nbatch=1, nstep=1, initial_state=x0,
                              compilation_cache=cache_dir)
    batch = next(iter(ds))
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, host(batch["initial_state"])[0].astype(np.float64),
                       FULLPHYSICS)
    mujoco.mj_step(model, data)
    assert data.ncon >= 4  # a contact step
    state = np.empty_like(x0)
    mujoco.mj_getState(model, data, state, FULLPHYSICS)
    np.testing.assert_allclose(host(batch["state"])[0, 0], state, rtol=0, atol=ONE_STEP_TOL)
    np.testing.assert_allclose(host(batch["sensordata"])[0, 0], data.sensordata,
                               rtol=ONE_STEP_SENSOR_RTOL, atol=ONE_STEP_TOL)
    np.testing.assert_array_equal(host(batch["control"]), np.zeros((1, 1, model.nu)))


# --- layout and bad input (no compilation) ---

LAYOUT_XML = """
<mujoco>
  <worldbody>
    <body pos="0 0 1"><freejoint/><geom size=".1"/></body>
    <body pos="1 0 1"><joint type="ball"/><geom type="capsule" fromto="0 0 0 0 0 -.3" size=".05"/>
      <body pos="0 0 -.3"><joint name="hinge" axis="0 1 0"/><geom size=".05"/></body></body>
    <body pos="2 0 1"><joint name="slide" type="slide"/><geom size=".1"/></body>
  </worldbody>
  <actuator>
    <general joint="hinge" dyntype="filter" dynprm="0.1"/>
    <general joint="slide" dyntype="integrator"/>
    <motor joint="slide"/>
  </actuator>
</mujoco>
"""


def test_physics_state_is_fullphysics_column_for_column():
    model = mujoco.MjModel.from_xml_string(LAYOUT_XML)
    assert model.na == 2
    data = mujoco.MjData(model)
    # a distinct value in every column (a layout check: quaternions need not be unit)
    expected = np.random.default_rng(0).permutation(
        np.arange(1, mujoco.mj_stateSize(model, FULLPHYSICS) + 1)) / 8.0
    mujoco.mj_setState(model, data, expected, FULLPHYSICS)
    mx = mjx.put_model(model, impl="jax")
    got = mjx.get_state(mx, mjx.put_data(model, data, impl="jax"), mjx_pool.PHYSICS)
    np.testing.assert_array_equal(np.asarray(got), expected)  # exact in float32 too
    # and back: the backend sets initial states with the same spec
    fresh = mjx.set_state(mx, mjx.make_data(model, impl="jax"), got, mjx_pool.PHYSICS)
    np.testing.assert_array_equal(np.asarray(mjx.get_state(mx, fresh, mjx_pool.PHYSICS)),
                                  np.asarray(got))


DELAYED_XML = """
<mujoco><worldbody><body><joint name="j"/><geom size=".1"/></body></worldbody>
<actuator><motor joint="j" delay="0.02" nsample="3"/></actuator></mujoco>
"""
IMPLICIT_XML = """
<mujoco><option integrator="implicit"/>
<worldbody><body><joint/><geom size=".1"/></body></worldbody></mujoco>
"""


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(model=DELAYED_XML), ValueError,
     "backend: 'mjx' cannot simulate this model: MJX does not simulate actuator and sensor "
     "delays (nhistory=8); use backend='cpu', which simulates it"),
    (dict(model=IMPLICIT_XML), ValueError,
     "model: MJX does not support a feature of this model: mjtIntegrator.mjINT_IMPLICIT; use "
     "backend='cpu'"),
    (dict(memory_fraction=2.0), ValueError,
     "memory_fraction: expected None or a number in (0, 1], got 2.0"),
    (dict(memory_fraction="half"), TypeError,
     "memory_fraction: expected None or a number in (0, 1], got str 'half'"),
    (dict(compilation_cache=True), TypeError,
     "compilation_cache: expected a directory path, None (default cache) or False (leave "
     "JAX's setting), got bool True"),
    (dict(jit=True, donate=False), TypeError,
     "SimDataset: unexpected keyword argument(s) ['donate', 'jit'] for backend='mjx' (its "
     "options are ['compilation_cache', 'memory_fraction'])"),
    (dict(impl="cuda"), ValueError,
     "impl: the older spelling of backend=, expected one of ('jax', 'warp', 'auto') or none, "
     "got 'cuda'"),
    (dict(impl=None), ValueError,
     "impl: the older spelling of backend=, expected one of ('jax', 'warp', 'auto') or none, "
     "got None"),
    (dict(naconmax=1000), TypeError,
     "SimDataset: unexpected keyword argument(s) ['naconmax'] for backend='mjx' (its options "
     "are ['compilation_cache', 'memory_fraction']); 'naconmax' is an option of "
     "backend='warp'"),
    (dict(backend="warp", naconmax=0), ValueError,
     "naconmax: expected None or a positive integer, got 0"),
])
def test_bad_input_fails_at_construction(cartpole, kwargs, error, message, monkeypatch):
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    kwargs = {"model": cartpole, "backend": "mjx", **kwargs}
    with pytest.raises(error) as info:
        simloader.SimDataset(kwargs.pop("model"), nbatch=2, nstep=2, **kwargs)
    assert str(info.value) == message


def test_models_differing_in_a_compiled_in_field_are_refused(cartpole):
    spec = mujoco.MjSpec.from_file(str(simloader.builtin_path("cartpole")))
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
    with pytest.raises(ValueError) as info:
        simloader.SimDataset(cartpole, backend="mjx", nbatch=2, nstep=2,
                             randomize=[cartpole, spec.compile()])
    assert str(info.value) == (
        "randomize[1]: model.opt.integrator differs from randomize[0], but MJX compiles it into "
        "the simulation; only numeric parameters may differ across the models")


def test_cameras_are_refused(cache_dir):
    with pytest.raises(ValueError, match="backend='mjx' cannot render"):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2,
                             compilation_cache=cache_dir, record=(simloader.Camera("front"),))


def test_auto_never_takes_mjx_for_cameras(cache_dir):
    ds = simloader.SimDataset("cartpole", backend="auto", nbatch=8192, nstep=2,
                              compilation_cache=cache_dir, record=(simloader.Camera("front"),))
    assert ds.stats["backend"] in ("warp", "cpu")
    assert "mjx ~" not in ds.config.backend_reason  # never among the estimates


# --- DataLoader workers ---

@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # JAX warns on any fork
@pytest.mark.parametrize("context", ["fork", None])
def test_forked_worker_is_refused_with_a_clear_message(faulty, context):
    ds, _, _ = faulty
    if context is None and multiprocessing.get_start_method() != "fork":
        pytest.skip("the default start method is not fork here")
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1,
                                         multiprocessing_context=context)
    with pytest.raises(RuntimeError, match=r"forked DataLoader worker: JAX is multithreaded.*"
                       r"num_workers=0.*multiprocessing_context='spawn'"):
        next(iter(loader))


def test_spawned_worker_gives_the_same_stream(cartpole, cache_dir, faulty):
    _, batches, _ = faulty
    # a fresh dataset of the same configuration: the worker loads its compilation from the cache
    ds = simloader.SimDataset(cartpole, backend="mjx", **faulty_kwargs(cartpole, cache_dir))
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1,
                                         multiprocessing_context="spawn")
    spawned = list(loader)
    assert len(spawned) == len(batches)
    for mine, ref in zip(spawned, batches):
        for key in KEYS:
            torch.testing.assert_close(mine[key].cpu(), ref[key].cpu(), rtol=0, atol=0,
                                       equal_nan=True)


# --- on the GPU (run on the device machine) ---

@pytest.fixture(scope="module")
def gpu_dataset(cache_dir):
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    # constructed before asking JAX for devices, so that simloader starts JAX if nobody has
    ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=4096, nstep=200,
                              control=controls.Uniform(), num_batches=3,
                              compilation_cache=cache_dir)
    if not any(d.platform == "gpu" for d in jax.devices()):
        pytest.skip("JAX sees no GPU")
    return ds


@pytest.mark.gpu
def test_gpu_placement_pointers_and_one_compilation(gpu_dataset):
    backend = gpu_dataset.make_backend()
    with traces() as seen:
        produced = [backend.produce(i) for i in range(3)]
        batches = [backend.deliver(p) for p in produced]
    assert len(seen) + gpu_dataset.stats["programs_loaded"] == 1
    for p, batch in zip(produced, batches):
        for key in KEYS:
            assert batch[key].device == torch.device("cuda", 0), key
            assert batch[key].data_ptr() == p.outputs[key].unsafe_buffer_pointer(), key
    backend.close()


@pytest.mark.gpu
def test_gpu_correct_under_a_non_default_torch_stream(gpu_dataset):
    backend = gpu_dataset.make_backend()
    stream = torch.cuda.Stream()
    copies, produced = [], []
    with torch.cuda.stream(stream):
        for i in range(3):
            produced.append(backend.produce(i))
            batch = backend.deliver(produced[-1])
            copies.append({k: v.clone() for k, v in batch.items()})  # read on the side stream
    torch.cuda.synchronize()
    for p, copy in zip(produced, copies):
        for key in KEYS:
            np.testing.assert_array_equal(host(copy[key]), np.asarray(p.outputs[key]), key)
    backend.close()


@pytest.mark.gpu
def test_gpu_delivery_to_another_device_and_dtype(gpu_dataset, cache_dir):
    ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=64, nstep=10, num_batches=1,
                              device="cpu", dtype=torch.float64, compilation_cache=cache_dir)
    batch = next(iter(ds))
    floats = set(batch) - {"diverged", *simloader.streams.KEYS}
    assert {(batch[k].device.type, batch[k].dtype) for k in floats} == {
        ("cpu", torch.float64)}
    assert batch["diverged"].device.type == "cpu"


@pytest.mark.gpu
def test_gpu_jax_leaves_memory_to_torch(gpu_dataset, checkout_env):
    # a fresh process: simloader is the first to start JAX there
    script = textwrap.dedent("""
        import torch, simloader
        ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=256, nstep=10,
                                  num_batches=1, compilation_cache=False)
        next(iter(ds))
        free, total = torch.cuda.mem_get_info()
        print(free / total)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, timeout=300, env=checkout_env())
    assert float(out.stdout.split()[-1]) > 0.5, out.stderr


def test_resolving_auto_backend_starts_jax_only_with_a_gpu_and_without_preallocation(
        checkout_env):
    # backend="auto" may ask JAX for its devices where a GPU may be, which starts JAX:
    # simloader's memory setting must be in place before, or JAX takes 75% of every GPU it
    # sees; where no GPU is visible it decides without importing JAX at all
    script = textwrap.dedent("""
        import os, sys, simloader
        from simloader import backends
        ds = simloader.SimDataset("cartpole", nbatch=2, nstep=2)
        print(ds.config.backend, backends.gpu_visible(), "jax" in sys.modules)
        if "jax" in sys.modules:
            from jax._src import xla_bridge
            print(xla_bridge.backends_are_initialized(),
                  os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"])
    """)
    env = {k: v for k, v in checkout_env().items() if k != "XLA_PYTHON_CLIENT_PREALLOCATE"}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, timeout=300, env=env)
    lines = [line.split() for line in out.stdout.splitlines()]
    resolved, gpu, imported = lines[0]
    if gpu == "False":
        assert (resolved, imported) == ("cpu", "False"), out.stdout
    elif imported == "True":
        assert lines[1] == ["True", "false"], out.stderr


def test_without_warp_mjx_prints_nothing_and_backend_warp_says_what_is_missing(checkout_env):
    # MJX prints "Failed to import warp" when it is imported without warp-lang: only a user who
    # asks for backend="warp" hears of it, inside the error
    script = textwrap.dedent("""
        import sys
        sys.modules["warp"] = None  # as if warp-lang were not installed
        import simloader
        ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2)
        print("backend", ds.config.backend)
        try:
            simloader.SimDataset("cartpole", backend="warp", nbatch=2, nstep=2)
        except ValueError as e:
            print("error", e)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, timeout=300, env=checkout_env())
    lines = out.stdout.splitlines()
    assert lines[0] == "backend mjx", out.stdout
    assert lines[1].startswith(
        "error backend: 'warp' cannot run here: the warp-lang package is not installed (pip "
        "install 'simloader[warp]')"), lines[1]
    assert len(lines) == 2 and "Failed to import" not in out.stderr


def test_iterator_left_open_at_exit_exits_quietly(checkout_env):
    # the generator is finalized after the modules are torn down: closing must not touch them
    script = textwrap.dedent("""
        import simloader
        ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=1, nstep=1, seed=0)
        it = iter(ds)
        next(it)
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300, env=checkout_env())
    assert out.returncode == 0, out.stderr
    assert "Exception ignored" not in out.stderr and "Traceback" not in out.stderr, out.stderr
