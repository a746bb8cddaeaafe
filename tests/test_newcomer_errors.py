"""Errors a new user met: each message says what was wrong and what to do."""

import gc
import re
import time

import pytest
import torch

import simloader
from simloader import randomize as dr


def make(model="cartpole", **kwargs):
    args = dict(backend="cpu", nbatch=2, nstep=3, nthread=1)
    args.update(kwargs)
    return simloader.SimDataset(model, **args)


def test_float32_policy_on_float64_observations_says_what_to_do():
    ds = make(policy=_LinearPolicy(), num_batches=1)
    with pytest.raises(TypeError) as e:
        next(iter(ds))
    msg = str(e.value)
    for part in ("policy", "dtype", "torch.float32", "torch.float64",
                 "SimDataset(..., dtype=torch.float32)", "policy.double()"):
        assert part in msg, (part, msg)
    # the fix works
    ds = make(policy=_LinearPolicy(), num_batches=1, dtype=torch.float32)
    assert next(iter(ds))["state"].dtype == torch.float32


class _LinearPolicy(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.linear = torch.nn.Linear(5, 1)  # cartpole: nstate = 1 + 2 + 2

    def forward(self, obs):
        return self.linear(obs["state"])


def test_policy_reading_an_unrecorded_key_is_told_about_record():
    ds = make(policy=lambda o: o["qpos"][:, :1], num_batches=1)
    with pytest.raises(KeyError) as e:
        next(iter(ds))
    msg = str(e.value)
    assert "'qpos'" in msg and "record=" in msg and "'state'" in msg and "'sensordata'" in msg
    ds = make(policy=lambda o: o["qpos"][:, :1], num_batches=1, record=["qpos"])
    assert "qpos" in next(iter(ds))


def test_batch_from_a_worker_keeps_its_views(tmp_path):
    ds = make(num_batches=1)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1)
    (batch,) = list(loader)
    assert isinstance(batch, simloader.batch.Batch)
    assert batch.view("qpos").shape == (2, 3, 2)
    # saved, it still loads without simloader's classes
    torch.save(batch, tmp_path / "b.pt")
    loaded = torch.load(tmp_path / "b.pt", weights_only=True)
    assert torch.equal(loaded["state"], batch["state"])


@pytest.mark.parametrize("batch_size", [1, 8])
def test_collation_message_is_true_for_the_batch_size_given(batch_size):
    ds = make(num_batches=20)
    it = iter(torch.utils.data.DataLoader(ds, batch_size=batch_size))
    with pytest.raises(TypeError) as e:
        next(it)
    msg = str(e.value)
    # the dataset's iterator (and its producer thread) ends now, not at a later collection
    del e, it
    gc.collect()
    assert "default batch_size=1 every" not in msg
    assert "batch_size=None" in msg and f"(here {batch_size})" in msg


def test_typo_of_a_keyword_says_did_you_mean():
    with pytest.raises(TypeError, match=re.escape("'n_batches' (did you mean 'num_batches'")):
        make(n_batches=3)


def test_zero_batches_are_refused():
    with pytest.raises(ValueError, match=re.escape(
            "num_batches: expected None or an integer >= 1, got 0")):
        make(num_batches=0)


def test_huge_nbatch_is_refused_before_building_tables():
    start = time.perf_counter()
    with pytest.raises(ValueError, match="nbatch, record: a batch needs"):
        make("humanoid", nbatch=10**7, nstep=100)
    assert time.perf_counter() - start < 2.0


def test_describe_lists_params_keys():
    ds = make(randomize=[dr.scale("body_mass", dr.Uniform(0.5, 1.5), on="pole")])
    text = ds.describe()
    (key,) = next(iter(ds))["params"]
    assert 'batch["params"]' in text and key in text
