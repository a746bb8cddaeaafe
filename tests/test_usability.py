"""The rough edges a newcomer hit: each is fixed or a clear message."""

import textwrap
import warnings

import mujoco
import pytest
import torch
from torch.utils.data import DataLoader

import simloader
from simloader import cli, controls
from simloader import randomize as dr

S = mujoco.mjtState


def cartpole(**kwargs):
    args = dict(backend="cpu", nbatch=2, nstep=3, control=controls.Uniform(), nthread=1,
                num_batches=2)
    args.update(kwargs)
    return simloader.SimDataset("cartpole", **args)


def test_auto_backend_without_a_gpu_does_not_start_jax(fresh_python):
    script = textwrap.dedent("""
        import sys, simloader
        ds = simloader.SimDataset("cartpole", nbatch=2, nstep=2, num_batches=1)
        next(iter(ds))
        print(ds.config.backend, "jax" in sys.modules, simloader.backends.gpu_visible())
    """)
    out, = fresh_python(script, [([], {})])
    backend, jax_imported, gpu = out.split()
    if gpu == "False":  # this machine: decided without JAX, hence no "Failed to import warp"
        assert (backend, jax_imported) == ("cpu", "False")


@pytest.mark.parametrize("workers", [0, 2])
def test_dataloader_without_batch_size_none_says_what_to_write(workers):
    with pytest.raises(TypeError, match=r"DataLoader\(ds, batch_size=None\)"):
        next(iter(DataLoader(cartpole(), num_workers=workers)))
    batch = next(iter(DataLoader(cartpole(), batch_size=None, num_workers=workers)))
    assert batch["state"].shape == (2, 3, 5) and isinstance(batch, dict)


def test_a_saved_batch_loads_without_simloader_types(tmp_path):
    torch.save(next(iter(cartpole())), tmp_path / "batch.pt")
    loaded = torch.load(tmp_path / "batch.pt", weights_only=True)
    assert isinstance(loaded, dict) and loaded["state"].shape == (2, 3, 5)


def test_control_spec_by_names_in_python_as_on_the_command_line():
    ds = cartpole(control=None, control_spec="ctrl|xfrc_applied")
    assert ds.config.control_spec == int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED)
    assert cli.parse_control_spec("ctrl | XFRC_APPLIED") == ds.config.control_spec
    with pytest.raises(ValueError, match=r"control_spec: unknown component 'ctl' \(did you mean "
                                         r"'ctrl'\?\); known: \['ctrl', "):
        cartpole(control_spec="ctl|xfrc_applied")


def test_randomize_is_part_of_the_public_api():
    assert "randomize" in simloader.__all__ and "randomize" in dir(simloader)
    assert simloader.randomize.Uniform is dr.Uniform


def test_normal_takes_mean_then_std_everywhere():
    assert controls.Normal(mean=1.0, std=2.0) == controls.Normal(std=2.0, mean=1.0)
    assert dr.Normal(1.0, 2.0) == dr.Normal(mean=1.0, std=2.0)
    # control generators take keywords only: a positional Normal(2.0) was a std, not a mean
    with pytest.raises(TypeError):
        controls.Normal(2.0)
    with pytest.raises(TypeError):
        controls.OrnsteinUhlenbeck(0.5, 0.1)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, "float16"])
def test_half_precision_is_refused_with_the_reason(dtype):
    with pytest.raises(ValueError, match=r"dtype: .*float16.* use torch.float32 or "
                                         r"torch.float64"):
        cartpole(dtype=dtype)


def test_float64_on_mjx_says_it_is_an_upcast():
    pytest.importorskip("mujoco.mjx")
    import jax
    if jax.config.jax_enable_x64:
        pytest.skip("JAX runs in float64 here")
    with pytest.warns(UserWarning, match="MJX simulates in float32"):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2, dtype=torch.float64,
                             compilation_cache=False)


def test_the_default_thread_split_needs_no_warning(monkeypatch):
    # torch's intra-op threads and the rollout threads together oversubscribe small machines
    # (2 cores: 2 + 2 threads made a CPU training loop 1.3x slower than 2 + 1): by default
    # the simulation takes half the cores when training may run on the CPU, all of them when
    # batches go to a GPU; nothing is said about a default
    from simloader import sharding, threads
    monkeypatch.setattr(threads, "available_cpus", lambda: 2)
    shard = sharding.Shard()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert threads.threads_per_worker(shard, None, torch_threads=2) == 1
        assert threads.threads_per_worker(shard, None, torch_threads=2,
                                           trains_on_cpu=False) == 2
        assert threads.threads_per_worker(shard, None, torch_threads=1) == 2
        assert threads.threads_per_worker(shard, 1, torch_threads=2) == 1
        simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=2)


def test_an_nthread_beyond_the_cores_is_said_at_the_users_line(monkeypatch):
    from simloader import threads
    monkeypatch.setattr(threads, "available_cpus", lambda: 2)
    with pytest.warns(RuntimeWarning, match="nthread=3 asks for more simulation threads than "
                                            "the 2 cores") as seen:
        simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=2, nthread=3)
    assert seen[0].filename == __file__
