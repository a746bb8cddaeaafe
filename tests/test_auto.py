"""One vocabulary for the engines (`backend="cpu" | "mjx" | "warp" | "auto"`), the older
spellings that still work and warn once, and `auto`'s rule: the fastest engine that runs here
for the model, the sizes and the machine."""

import textwrap
import types

import numpy as np
import pytest

import simloader
from simloader import backends, identity
from simloader.backends import auto
from simloader.backends.contract import Job


def test_cpu_is_the_engine_of_mujoco_on_cpu_threads():
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3, num_batches=1)
    assert ds.config.backend == "cpu" and ds.stats["backend"] == "cpu"
    assert "simulated by: backend='cpu' (mujoco.batch on CPU threads; chosen: asked)" \
        in ds.describe()


OLD_SPELLINGS = [
    (dict(backend="rollout"), "cpu", "backend='rollout' is the older spelling of backend='cpu'"),
    (dict(backend="mjx", impl="jax"), "mjx",
     "backend='mjx', impl='jax' is the older spelling of backend='mjx'"),
    (dict(backend="mjx", impl="warp"), "warp",
     "backend='mjx', impl='warp' is the older spelling of backend='warp'"),
]


@pytest.mark.parametrize("kwargs, new, message", OLD_SPELLINGS,
                         ids=[n for _, n, _ in OLD_SPELLINGS])
def test_older_spellings_still_work_and_warn_once_in_a_fresh_process(fresh_python, kwargs,
                                                                      new, message):
    pytest.importorskip("mujoco.mjx")
    if new == "warp":
        pytest.importorskip("mujoco_warp")
    script = textwrap.dedent(f"""
        import warnings, simloader
        warnings.simplefilter("always")
        with warnings.catch_warnings(record=True) as caught:
            for _ in range(2):
                ds = simloader.SimDataset("cartpole", nbatch=2, nstep=2, num_batches=1,
                                          **{kwargs!r})
        batch = next(iter(ds))
        future = [str(w.message) for w in caught if w.category is FutureWarning]
        print(ds.config.backend, len(future), future[0] if future else "")
        print(caught[0].filename if caught else "")
    """)
    out, = fresh_python(script, [([], {"SIMLOADER_WARP_ON_CPU": "1"})])
    first, where = out.strip().splitlines()[-2:]
    backend, count, said = first.split(" ", 2)
    assert (backend, count) == (new, "1"), out  # once per process, not once per dataset
    assert said.startswith(message) and "still works" in said
    assert where.endswith("<string>")  # the warning points at the user's line


def test_impl_with_another_backend_is_refused():
    with pytest.raises(ValueError, match=r"impl: 'jax' is the older way to name a GPU engine "
                                         r"and means nothing with backend='cpu'; drop it"):
        simloader.SimDataset("cartpole", backend="cpu", impl="jax", nbatch=2, nstep=2)


def test_an_option_of_another_engine_is_refused_by_name():
    with pytest.raises(TypeError, match=r"\['naconmax'\] for backend='cpu' \(its options are "
                                        r"\[\]\); 'naconmax' is an option of backend='warp'"):
        simloader.SimDataset("cartpole", backend="cpu", naconmax=10, nbatch=2, nstep=2)


def test_auto_without_a_gpu_weighs_the_cpu_engine_against_mjx_on_jax_cpu(monkeypatch):
    monkeypatch.delenv("SIMLOADER_WARP_ON_CPU", raising=False)
    import torch
    if torch.cuda.is_available():
        pytest.skip("a GPU is here")
    pytest.importorskip("mujoco.mjx")
    # contacts: MuJoCo's own threads (MJX on the CPU was 7x slower on the 2-core machine)
    ds = simloader.SimDataset("humanoid", nbatch=8192, nstep=2)
    assert ds.config.backend == "cpu"
    said = ds.config.backend_reason
    assert "estimated steps/s for nbatch=8192" in said and "mjx ~" in said
    assert "warp ~" not in said  # MuJoCo Warp needs a CUDA GPU: not a candidate
    # a tiny batch stays on the CPU engine (XLA's fixed cost per step); a large batch of the
    # tiny contact-free cart-pole goes to MJX on JAX's CPU, measured 1.1-1.2x faster
    assert auto.choose("auto", False, probe("cartpole", 2)).backend == "cpu"
    assert auto.choose("auto", False, probe("cartpole", 4096)).backend == "mjx"


def test_an_endless_stream_counts_start_up_against_its_first_minute(monkeypatch):
    monkeypatch.delenv("SIMLOADER_WARP_ON_CPU", raising=False)
    import torch
    if torch.cuda.is_available():
        pytest.skip("a GPU is here")
    pytest.importorskip("mujoco.mjx")
    monkeypatch.setattr(auto.threads, "available_cpus", lambda: 2)
    # the cart-pole's step as timed on a quiet 2-core machine (timed live, a busy machine
    # would move the crossing)
    monkeypatch.setattr(auto, "cpu_step_seconds", lambda model: 1.6e-6)
    # 64 cart-poles: MJX on JAX's CPU estimated a few % faster in the steady state, which
    # would not repay its compilation (8-9 s on the 2-core machine) within a minute
    monkeypatch.setattr(auto, "FIRST_MINUTE_S", 1e12)  # forever
    monkeypatch.setattr(auto, "NEAR_TIE", 1.0)  # no ties
    forever = auto.choose("auto", False, probe("cartpole", 64))
    assert forever.backend == "mjx", forever.reason  # the rule before: start-up never counted
    monkeypatch.setattr(auto, "FIRST_MINUTE_S", 60.0)
    minute = auto.choose("auto", False, probe("cartpole", 64))
    assert minute.backend == "cpu", minute.reason  # a minute alone decides it
    monkeypatch.setattr(auto, "NEAR_TIE", 0.9)
    minute = auto.choose("auto", False, probe("cartpole", 64))
    assert minute.backend == "cpu", minute.reason
    assert "over an endless stream's first 60 s with a first run's start-up" in minute.reason
    # 256 cart-poles: MJX ahead by more than the rule's error (measured 1.5x): compiled
    assert auto.choose("auto", False, probe("cartpole", 256)).backend == "mjx"


def test_a_near_tie_goes_to_the_engine_that_starts_first(monkeypatch):
    everything_runs(monkeypatch)
    monkeypatch.setattr(auto.threads, "available_cpus", lambda: 16)
    monkeypatch.setattr(auto, "cpu_step_seconds", lambda model: 3.0e-6)  # H200's cart-pole
    rates = {}
    for name in ("cpu", "mjx", "warp"):
        engine = type(backends.engine(name))
        monkeypatch.setattr(engine, "estimate", lambda self, job, n=name: rates[n])
    rates.update(cpu=1.0e6, mjx=1.05e6, warp=0.5e6)  # MJX 5% ahead after its start-up
    assert auto.choose("auto", False, probe("cartpole", 512)).backend == "cpu"
    rates.update(mjx=1.3e6)  # clearly ahead
    assert auto.choose("auto", False, probe("cartpole", 512)).backend == "mjx"


def everything_runs(monkeypatch):
    """`auto` as on a GPU machine with both GPU engines (the rule alone is tested: no engine
    is built here)."""
    for name in ("mjx", "warp"):
        cls = type(backends.engine(name))
        monkeypatch.setattr(cls, "missing", lambda self: None)
        monkeypatch.setattr(cls, "confirm", lambda self: None)
    # MJX estimates as on a GPU (JAX's CUDA plugin there)
    monkeypatch.setattr(type(backends.engine("mjx")), "_gpu", staticmethod(lambda: True))


def probe(name, nbatch, **kwargs):
    return types.SimpleNamespace(model=simloader.load_model(name), nbatch=nbatch, nstep=100,
                                 num_batches=kwargs.get("num_batches"),
                                 observations=kwargs.get("observations", ()),
                                 policy=kwargs.get("policy"))


def test_auto_rule_small_batches_on_the_cpu_large_ones_on_the_gpu(monkeypatch):
    everything_runs(monkeypatch)
    monkeypatch.setattr(auto.threads, "available_cpus", lambda: 16)
    for name in ("cartpole", "humanoid"):
        small = auto.choose("auto", False, probe(name, 16))
        assert small.backend == "cpu", small.reason
        assert "estimated steps/s for nbatch=16 on 16 cores" in small.reason
    # contact-free: XLA's fused step; contacts: MuJoCo Warp
    assert auto.choose("auto", False, probe("cartpole", 8192)).backend == "mjx"
    assert auto.choose("auto", False, probe("humanoid", 8192)).backend == "warp"
    # the older impl="auto": GPU engines only, whatever the size
    assert auto.choose("auto", True, probe("humanoid", 16)).backend in ("mjx", "warp")


def test_auto_rule_never_takes_mjx_for_cameras_or_a_policy(monkeypatch):
    everything_runs(monkeypatch)
    cameras = simloader.observe.parse(simloader.load_model("cartpole"),
                                      ("state", simloader.Camera("front")))
    for kwargs in ({"observations": cameras}, {"policy": lambda o: o}):
        choice = auto.choose("auto", False, probe("cartpole", 8192, **kwargs))
        assert choice.backend == "warp", choice.reason


def test_a_short_stream_counts_the_engines_start_up(monkeypatch):
    everything_runs(monkeypatch)
    monkeypatch.setattr(auto.threads, "available_cpus", lambda: 16)
    # 8192 cart-poles x 100 steps: endless on MJX; two batches finish sooner on the CPU than
    # a first MJX compilation (4 s) would
    assert auto.choose("auto", False, probe("cartpole", 8192)).backend == "mjx"
    short = auto.choose("auto", False, probe("cartpole", 8192, num_batches=2))
    assert short.backend == "cpu" and "with a first run's start-up" in short.reason


def test_auto_estimates_grow_with_the_batch_on_the_gpu_only():
    def rates(name):
        return [backends.engine(name).estimate(Job(step_s=20e-6, nbatch=n, contacts=True,
                                                   cores=16, policy=False, cameras=False))
                for n in (64, 1024, 8192)]
    cpu, warp = rates("cpu"), rates("warp")
    assert cpu[0] == cpu[1] == cpu[2]  # 16 cores busy from 16 trajectories on
    assert warp[0] < warp[1] < warp[2]


def test_cpu_step_time_is_measured_per_model():
    cartpole = auto.cpu_step_seconds(simloader.load_model("cartpole"))
    humanoid = auto.cpu_step_seconds(simloader.load_model("humanoid"))
    assert 0 < cartpole < humanoid < 1e-2


def test_has_contacts():
    assert not auto.has_contacts(simloader.load_model("cartpole"))
    assert auto.has_contacts(simloader.load_model("humanoid"))


def test_a_state_saved_with_the_older_names_resumes():
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3, num_batches=4,
                              control=simloader.controls.Uniform())
    it = iter(ds)
    next(it)
    state = ds.state_dict()
    expected = next(it)["state"]
    old = dict(state, config=dict(state["config"], backend="rollout"))
    again = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3, num_batches=4,
                                 control=simloader.controls.Uniform())
    again.load_state_dict(old)
    assert np.array_equal(next(iter(again))["state"], expected)
    # an MJX state of before: backend "mjx" with the option impl
    saved = {"backend": "mjx", "backend_options": {"impl": "warp", "njmax": 4}}
    assert identity.upgraded(saved) == {"backend": "warp", "backend_options": {"njmax": 4}}
    saved = {"backend": "mjx", "backend_options": {"impl": "jax"}}
    assert identity.upgraded(saved) == {"backend": "mjx", "backend_options": {}}


def test_cli_speaks_the_same_words(capsys):
    from simloader import cli
    cli.main(["quickstart", "--backend", "cpu", "--nbatch", "4", "--nstep", "3",
              "--batches", "2"])
    out = capsys.readouterr().out
    assert "backend 'cpu' (mujoco.batch on CPU threads), chosen: asked" in out
    assert cli.engines_here()[0] == "cpu"


def test_the_only_engine_that_runs_is_still_asked_whether_it_simulates_the_model(monkeypatch):
    # the GPU engines only (impl='auto'), MuJoCo Warp missing: MJX is the one engine left,
    # and a model it refuses is refused at construction, naming why (engines' checks rely on
    # the chosen engine having been asked)
    everything_runs(monkeypatch)
    monkeypatch.setattr(type(backends.engine("warp")), "missing",
                        lambda self: "no MuJoCo Warp here")
    mjx = type(backends.engine("mjx"))
    monkeypatch.setattr(mjx, "refuses_model", lambda self, model: "a feature it lacks")
    with pytest.raises(ValueError, match=r"no engine can run this dataset here \(.*no MuJoCo "
                                         r"Warp here.*; mjx: a feature it lacks\)"):
        auto.choose("auto", True, probe("cartpole", 64))
    monkeypatch.setattr(mjx, "refuses_model", lambda self, model: None)
    assert auto.choose("auto", True, probe("cartpole", 64)).backend == "mjx"
