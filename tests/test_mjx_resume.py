"""Resuming an MJX stream with continuing episodes: the carry (last physics state, solver
warmstart, restart rows, randomized values and variants) goes through JSON, and the resumed
stream equals the uninterrupted one exactly. Exactly, not within a tolerance: the checkpoint
holds the carry's float32 bits, an uninterrupted stream continues from the same carry
through the same compiled function, and JAX on the CPU is deterministic.

Randomized parameters with continuing episodes are checked here too: values last an episode,
a trajectory that restarts draws fresh ones, and the chunks match MuJoCo C on each
trajectory's model.
"""

import json

import numpy as np
import pytest
import torch

mjx = pytest.importorskip("mujoco.mjx")

import simloader  # noqa: E402
from test_mjx import (CONTACT_FREE_TOL, c_rollout, continued_kwargs, host,  # noqa: E402
                      pole_mass_models)
from test_mjx_randomize import variant_kwargs  # noqa: E402
from test_randomize import SPEC, equivalent_models  # noqa: E402

StatefulDataLoader = pytest.importorskip("torchdata.stateful_dataloader").StatefulDataLoader

DIVERGING = 1


def params_kwargs(cache_dir):
    """The randomized cart-pole, continuing, one trajectory given a NaN control every batch."""
    control = np.random.default_rng(1).uniform(-1, 1, (4, 20, 1))
    control[DIVERGING, 7] = np.nan
    return dict(nbatch=4, nstep=20, num_batches=4, control=control, randomize=SPEC, seed=2,
                initial_state=simloader.initial.Perturbed(), continue_episodes=True,
                compilation_cache=cache_dir)


CONFIGS = {
    "params": lambda cache_dir: ("cartpole", params_kwargs(cache_dir)),
    "variants": lambda cache_dir: ("cartpole", variant_kwargs(cache_dir)),
    "model list": lambda cache_dir: (pole_mass_models()[0],
                                     continued_kwargs(pole_mass_models(), cache_dir)),
}


def make(config, cache_dir):
    model, kwargs = CONFIGS[config](cache_dir)
    return simloader.SimDataset(model, backend="mjx", **kwargs)


@pytest.fixture(scope="module")
def datasets(cache_dir):
    """One dataset per configuration, compiled once and iterated by several tests."""
    return {}


def dataset(datasets, config, cache_dir):
    if config not in datasets:
        datasets[config] = make(config, cache_dir)
    return datasets[config]


def flat(batch):
    out = {k: v for k, v in batch.items() if k != "params"}
    out.update({f"params/{k}": v for k, v in batch.get("params", {}).items()})
    return out


def run(loader, n=None):
    out = []
    for batch in loader:
        out.append({k: v.clone() for k, v in flat(batch).items()})
        if n is not None and len(out) == n:
            break
    return out


@pytest.mark.parametrize("config, k", [("params", 1), ("params", 3), ("variants", 1),
                                       ("model list", 2)])
def test_resume_after_k_batches_equals_the_uninterrupted_stream(datasets, cache_dir, config, k):
    ds = dataset(datasets, config, cache_dir)
    full = run(StatefulDataLoader(ds, batch_size=None))
    loader = StatefulDataLoader(ds, batch_size=None)
    first = run(loader, k)
    saved = json.loads(json.dumps(loader.state_dict()))  # JSON round trip
    del loader
    # a new dataset of the same configuration (its compilation comes from JAX's cache)
    resumed = StatefulDataLoader(make(config, cache_dir), batch_size=None)
    resumed.load_state_dict(saved)
    rest = run(resumed)
    assert len(first) + len(rest) == len(full) == ds.config.num_batches
    for index, (mine, ref) in enumerate(zip(first + rest, full)):
        assert mine.keys() == ref.keys()
        for key in ref:  # bit for bit (the NaN control of the diverging row included)
            torch.testing.assert_close(mine[key], ref[key], rtol=0, atol=0, equal_nan=True,
                                       msg=f"batch {index}, {key}")
    # the first trajectory (never diverging) continued across the interruption
    assert torch.equal(rest[0]["initial_state"][0], first[-1]["state"][0, -1])


def test_checkpoint_is_small_json(datasets, cache_dir):
    ds = dataset(datasets, "params", cache_dir)
    it = iter(ds)
    next(it)
    state = ds.state_dict()
    trajectories = state["trajectories"]
    assert sorted(trajectories) == ["params", "qacc_warmstart", "restart", "state"]
    assert sorted(trajectories["params"]) == sorted(p.key for p in SPEC)
    assert len(json.dumps(state)) < 4096
    it.close()


@pytest.fixture(scope="module")
def params_batches(datasets, cache_dir):
    return list(dataset(datasets, "params", cache_dir))


def test_values_last_an_episode_and_a_restart_draws_fresh_ones(params_batches):
    ok = np.arange(4) != DIVERGING
    for prev, nxt in zip(params_batches, params_batches[1:]):
        np.testing.assert_array_equal(host(nxt["diverged"]), ~ok)
        for key in prev["params"]:
            before, after = host(prev["params"][key]), host(nxt["params"][key])
            np.testing.assert_array_equal(after[ok], before[ok])
            assert np.all(after[DIVERGING] != before[DIVERGING]), key


def test_randomized_chunks_match_mujoco_on_each_trajectorys_model(params_batches):
    ok = np.flatnonzero(np.arange(4) != DIVERGING)
    params = {k: host(v)[ok].astype(np.float64) for k, v in params_batches[0]["params"].items()}
    model = simloader.load_model("cartpole")
    control = np.concatenate([host(b["control"]) for b in params_batches], axis=1)
    state, _ = c_rollout(equivalent_models(model, params),
                         host(params_batches[0]["initial_state"])[ok], control[ok])
    got = np.concatenate([host(b["state"])[ok] for b in params_batches], axis=1)
    np.testing.assert_allclose(got, state, rtol=0, atol=CONTACT_FREE_TOL)
