"""Resume: interrupting after k batches and resuming yields the uninterrupted stream, bit for bit."""

import json
import pathlib
import textwrap

import numpy as np
import pytest
import torch

import simloader
from simloader import controls
from simloader import randomize as dr
from test_randomize import SPEC, pole_variant

StatefulDataLoader = pytest.importorskip("torchdata.stateful_dataloader").StatefulDataLoader


def make(num_batches, continue_episodes=False, seed=0):
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=3, nstep=4,
                                control=controls.Uniform(), nthread=1, seed=seed,
                                initial_state=simloader.initial.Perturbed(),
                                continue_episodes=continue_episodes, num_batches=num_batches)


def states(loader, n=None):
    out = []
    for batch in loader:
        out.append(batch["state"].clone())
        if n is not None and len(out) == n:
            break
    return out


@pytest.mark.parametrize("workers", [0, 2])
@pytest.mark.parametrize("k", [0, 1, 10, 257])
@pytest.mark.parametrize("continue_episodes", [False, True])
def test_resume_after_k_batches(k, workers, continue_episodes):
    total = k + 3
    full = states(StatefulDataLoader(make(total, continue_episodes), batch_size=None,
                                     num_workers=workers))
    loader = StatefulDataLoader(make(total, continue_episodes), batch_size=None,
                                num_workers=workers)
    first = states(loader, k) if k else []
    saved = json.loads(json.dumps(loader.state_dict()))  # JSON round trip
    del loader
    resumed_loader = StatefulDataLoader(make(total, continue_episodes), batch_size=None,
                                        num_workers=workers)
    resumed_loader.load_state_dict(saved)
    rest = states(resumed_loader)
    assert len(first) + len(rest) == total
    for a, b in zip(first + rest, full):
        assert torch.equal(a, b)


def timeline(loader, epochs, stop_after=None):
    """What `epochs` passes over `loader` deliver: each batch's state, and None where an epoch
    ends; stops after `stop_after` of these tokens."""
    out = []
    for _ in range(epochs):
        for batch in loader:
            out.append(batch["state"].clone())
            if len(out) == stop_after:
                return out
        out.append(None)
        if len(out) == stop_after:
            return out
    return out


@pytest.mark.parametrize("workers", [0, 2])
@pytest.mark.parametrize("position", [2, 4, 5, 10, 12])
@pytest.mark.parametrize("continue_episodes", [False, True])
def test_resume_at_any_point_of_any_epoch(position, workers, continue_episodes):
    # 3 epochs of 4 batches; position 4: after the last batch of epoch 0, before its end was
    # seen; 5 and 10: at the end of an epoch (before the fix, with 0 workers, the resumed
    # loader delivered an empty epoch there: the position was read at the first next())
    def loader():
        return StatefulDataLoader(make(4, continue_episodes), batch_size=None,
                                  num_workers=workers)

    full = timeline(loader(), 3)
    interrupted = loader()
    first = timeline(interrupted, 3, stop_after=position)
    saved = json.loads(json.dumps(interrupted.state_dict()))
    resumed = loader()
    resumed.load_state_dict(saved)
    rest = timeline(resumed, 3 - first.count(None))
    got = first + rest
    assert [t is None for t in got] == [t is None for t in full]
    for a, b in zip(got, full):
        assert a is None or torch.equal(a, b)


def test_dataset_state_is_small_json():
    ds = make(None, continue_episodes=True)
    it = iter(ds)
    next(it)
    text = json.dumps(ds.state_dict())
    assert len(text) < 4096
    it.close()


def test_resume_in_a_new_process(tmp_path, fresh_python):
    script = textwrap.dedent("""
        import json, sys, numpy as np
        sys.path.insert(0, %r)
        from test_resume import make, states, StatefulDataLoader
        loader = StatefulDataLoader(make(8, True), batch_size=None, num_workers=2)
        if sys.argv[1] == "save":
            states(loader, 5)
            json.dump(loader.state_dict(), open(sys.argv[2], "w"))
        else:
            loader.load_state_dict(json.load(open(sys.argv[2])))
            np.save(sys.argv[3], np.stack([s.numpy() for s in states(loader)]))
    """ % str(pathlib.Path(__file__).parent))
    state, out = tmp_path / "state.json", tmp_path / "rest.npy"
    fresh_python(script, [(["save", state], {})])
    fresh_python(script, [(["load", state, out], {})])
    full = states(StatefulDataLoader(make(8, True), batch_size=None, num_workers=2))
    np.testing.assert_array_equal(np.load(out), np.stack([s.numpy() for s in full[5:]]))


def test_mismatched_configuration_is_a_clear_error():
    saved = make(5).state_dict()
    with pytest.raises(ValueError, match="state_dict: the saved stream has another "
                                         "configuration: seed is 1 here but 0 in the state"):
        make(5, seed=1).load_state_dict(saved)
    expected = f"state_dict: expected a simloader state of version {simloader.resume.VERSION}"
    with pytest.raises(ValueError, match=expected):
        make(5).load_state_dict({"version": 99})


def other_pole_variant(spec, rng):
    spec.geom("pole").fromto = [0, 0, 0, 0, 0, rng.uniform(2.0, 3.0)]
    return spec


BASE = dict(control=controls.Uniform(), initial_state=simloader.initial.Perturbed(),
            randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole")])
CHANGES = {  # one change of what the stream is made of, and the name the refusal gives it
    "control generator": (dict(control=controls.PiecewiseConstant(hold=2)), "control"),
    "control parameter": (dict(control=controls.Uniform(low=-0.5)), "control"),
    "control array": (dict(control=np.full((1, 1, 1), 0.25)), "control"),
    "initial generator": (dict(initial_state=simloader.initial.Perturbed(qpos_std=0.3)),
                          "initial_state"),
    "initial array": (dict(initial_state=np.zeros((1, 5))), "initial_state"),
    "randomized object": (dict(randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0),
                                                   on="cart")]), "randomize"),
    "distribution": (dict(randomize=[dr.scale("body_mass", dr.Uniform(0.5, 3.0), on="pole")]),
                     "randomize"),
    "variant pool": (dict(randomize=dr.Variants(pole_variant, count=4)), "randomize"),
    "dtype": (dict(dtype=torch.float32), "dtype"),
}


def configured(**changes):
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=3, nstep=4, nthread=1,
                                continue_episodes=True, num_batches=5, **{**BASE, **changes})


@pytest.mark.parametrize("change", sorted(CHANGES))
def test_resuming_another_configuration_is_refused_naming_it(change):
    # before the fix: control, initial state and randomization were not in the fingerprint;
    # a randomized stream resumed into another one failed late with KeyError('body_mass[cart]')
    changes, name = CHANGES[change]
    ds = configured()
    it = iter(ds)
    next(it)
    saved = json.loads(json.dumps(ds.state_dict()))
    it.close()
    configured().load_state_dict(saved)  # the same configuration, made anew, resumes
    with pytest.raises(ValueError, match=rf"the saved stream has another configuration: "
                                         rf"(.* )?{name}\S* is "):
        configured(**changes).load_state_dict(saved)


def test_variant_pools_of_other_functions_differ():
    a = configured(randomize=dr.Variants(pole_variant, count=4)).state_dict()
    with pytest.raises(ValueError, match="randomize"):
        configured(randomize=dr.Variants(other_pole_variant, count=4)).load_state_dict(a)


def test_fingerprint_covers_stream_changing_backend_options_only():
    import dataclasses
    from simloader import identity, resume

    unchanged = dict([identity.STREAM_UNCHANGED])  # an engine marks what keeps the stream

    @dataclasses.dataclass(frozen=True)
    class Options:  # as an engine resolves its options (MJX's and Warp's together)
        njmax: int
        compilation_cache: str = dataclasses.field(default="/a", metadata=unchanged)
        memory_fraction: float = dataclasses.field(default=None, metadata=unchanged)

    config = configured().config
    state = {"version": resume.VERSION,
             "config": identity.fingerprint(dataclasses.replace(config, options=Options(8)))}
    # where JAX caches and how much memory it takes, or why an engine was chosen: same stream
    resume.check(dataclasses.replace(config, options=Options(8, "/b", 0.5),
                                     backend_reason="auto: ..."), state)
    with pytest.raises(ValueError, match=r"backend_options.njmax is 9 here but 8"):
        resume.check(dataclasses.replace(config, options=Options(9)), state)


def test_fingerprint_is_the_same_in_fresh_processes(fresh_python):
    script = textwrap.dedent("""
        import json, sys
        sys.path.insert(0, %r)
        from test_resume import configured
        print(json.dumps(configured().state_dict()["config"], sort_keys=True))
    """ % str(pathlib.Path(__file__).parent))
    first, second = fresh_python(script, [([], {}), ([], {"PYTHONHASHSEED": "7"})])
    assert first == second
    assert json.loads(first) == json.loads(json.dumps(configured().state_dict()["config"]))


@pytest.mark.parametrize("randomize", [SPEC, dr.Variants(pole_variant, count=4)],
                         ids=["params", "variants"])
def test_resume_continues_each_trajectory_on_its_randomized_model(randomize):
    def make_randomized():
        return simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=10,
                                    control=controls.Uniform(), randomize=randomize,
                                    continue_episodes=True, num_batches=5, nthread=1)

    def run(loader, n=None):
        out = []
        for batch in loader:
            out.append((batch["state"].clone(), {k: v.clone() for k, v in batch["params"].items()}))
            if len(out) == n:
                break
        return out

    full = run(StatefulDataLoader(make_randomized(), batch_size=None))
    loader = StatefulDataLoader(make_randomized(), batch_size=None)
    first = run(loader, 2)
    saved = json.loads(json.dumps(loader.state_dict()))
    resumed = StatefulDataLoader(make_randomized(), batch_size=None)
    resumed.load_state_dict(saved)
    for (state, params), (ref_state, ref_params) in zip(first + run(resumed), full):
        assert torch.equal(state, ref_state)
        assert params.keys() == ref_params.keys()
        assert all(torch.equal(params[k], ref_params[k]) for k in params)


def test_continuing_trajectories_are_one_structure_and_refuse_another_engines_rows():
    """Every engine checkpoints its continuing trajectories as {spec, rows, fresh, params};
    rows of another mjtState spec are refused by name, not misread."""
    from simloader import resume as resume_mod
    rows, fresh = np.arange(12.0).reshape(3, 4), np.array([True, False, True])
    encoded = resume_mod.encode_trajectories(7, rows, fresh, {"mass": np.ones((3, 1))})
    assert sorted(encoded) == ["fresh", "params", "rows", "spec"]
    back_rows, back_fresh, params = resume_mod.decode_trajectories(encoded, 7)
    assert np.array_equal(back_rows, rows) and np.array_equal(back_fresh, fresh)
    assert np.array_equal(params["mass"], np.ones((3, 1)))
    with pytest.raises(ValueError, match="spec 7.*spec 24639"):
        resume_mod.decode_trajectories(encoded, 24639)
