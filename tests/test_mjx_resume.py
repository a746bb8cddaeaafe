"""Resuming an MJX stream with continuing episodes: the carry (last physics state, solver
warmstart, restart rows, randomized values and variants) goes through JSON, and the resumed
stream equals the uninterrupted one exactly. Exactly, not within a tolerance: the checkpoint
holds the carry's float32 bits, an uninterrupted stream continues from the same carry
through the same compiled function, and JAX on the CPU is deterministic.

The configurations are those of tests/test_mjx.py and tests/test_mjx_randomize.py (model list,
randomized parameters, variants; one trajectory restarting in every batch), whose compilations
come from JAX's persistent cache when those modules ran first.
"""

import json

import pytest
import torch

mjx = pytest.importorskip("mujoco.mjx")

import simloader  # noqa: E402
from test_mjx import continued_kwargs, pole_mass_models  # noqa: E402
from test_mjx_randomize import params_kwargs, variant_kwargs  # noqa: E402
from test_randomize import SPEC  # noqa: E402

StatefulDataLoader = pytest.importorskip("torchdata.stateful_dataloader").StatefulDataLoader

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
def dataset(cache_dir):
    """`dataset(config)`: one dataset per configuration, shared by the tests here."""
    made = {}

    def get(config):
        if config not in made:
            made[config] = make(config, cache_dir)
        return made[config]

    return get


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


def resume(ds, k, into):
    """The stream of `ds` interrupted after `k` batches, saved through JSON and resumed by
    `into` (a dataset of the same configuration), next to the uninterrupted stream."""
    full = run(StatefulDataLoader(ds, batch_size=None))
    loader = StatefulDataLoader(ds, batch_size=None)
    first = run(loader, k)
    saved = json.loads(json.dumps(loader.state_dict()))  # JSON round trip
    del loader
    resumed = StatefulDataLoader(into, batch_size=None)
    resumed.load_state_dict(saved)
    return first, run(resumed), full


def assert_same_stream(first, rest, full):
    assert len(first) + len(rest) == len(full)
    for index, (mine, ref) in enumerate(zip(first + rest, full)):
        assert mine.keys() == ref.keys()
        for key in ref:  # bit for bit
            torch.testing.assert_close(mine[key], ref[key], rtol=0, atol=0, equal_nan=True,
                                       msg=f"batch {index}, {key}")
    # the first trajectory (never diverging) continued across the interruption
    assert torch.equal(rest[0]["initial_state"][0], first[-1]["state"][0, -1])


@pytest.mark.parametrize("config, k", [("params", 1), ("params", 2), ("variants", 1),
                                       ("model list", 2)])
def test_resume_after_k_batches_equals_the_uninterrupted_stream(dataset, config, k):
    # the resumed iterator gets the trajectories from the saved state alone: each iterator
    # makes its own backend (the dataset keeps only the compiled function)
    ds = dataset(config)
    assert_same_stream(*resume(ds, k, into=ds))


def test_resume_in_a_new_dataset(dataset, cache_dir):
    # as a new process would: a dataset of the same configuration, compiled anew (or loaded
    # from JAX's cache)
    assert_same_stream(*resume(dataset("params"), 1, into=make("params", cache_dir)))


def test_checkpoint_is_small_json(dataset):
    ds = dataset("params")
    it = iter(ds)
    next(it)
    state = ds.state_dict()
    trajectories = state["trajectories"]
    assert sorted(trajectories) == ["fresh", "params", "rows", "spec"]
    assert sorted(trajectories["params"]) == sorted(p.key for p in SPEC)
    assert len(json.dumps(state)) < 4096
    it.close()
