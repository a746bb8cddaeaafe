"""Episodes that end (`terminate=`) in stores: the flags kept, transitions never across a
reset, a stored trajectory regenerated with its resets, Minari episodes split at the resets
with Minari's terminations and truncations."""

import numpy as np
import pytest
import torch

import simloader
from simloader import controls
from simloader import terminate as T

NBATCH, NSTEP = 6, 60


def dataset(**kwargs):
    return simloader.SimDataset("cartpole", nbatch=NBATCH, nstep=NSTEP, seed=4, backend="cpu",
                                control=controls.Uniform(), num_batches=2,
                                terminate=[T.Outside("hinge", -0.2, 0.2), T.TimeLimit(25)],
                                **kwargs)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("episodes") / "store"
    simloader.write(dataset(), path, batches=2, progress=False)
    return simloader.StoredDataset(path)


def expected_pairs(stored):
    """(s_t, a_t, s_t+1) of every stored transition that is physics, in store order."""
    out = []
    for i in range(len(stored)):
        item = stored[i]
        state, control, first = item["state"], item["control"], item["first"]
        for f in range(NSTEP):
            if first[f]:
                continue  # the fresh state is not the step from the frame before
            before = item["initial_state"] if f == 0 else state[f - 1]
            out.append((before, control[f], state[f]))
    return out


def test_the_store_keeps_the_flags(store):
    assert {"terminated", "truncated", "first"} <= set(store.keys)
    batch = next(iter(dataset()))
    for row in range(NBATCH):
        for key in ("terminated", "truncated", "first"):
            assert torch.equal(store[row][key], batch[key][row])
    assert sum(int(store[i]["first"].sum()) for i in range(len(store))) >= NBATCH


def test_transitions_never_pair_a_frame_with_the_reset_after_it(store):
    pairs = store.transitions()
    want = expected_pairs(store)
    assert len(pairs) == len(want) < len(store) * NSTEP
    got = pairs.gather(range(len(pairs)))
    assert not torch.isnan(got["control"]).any()  # a fresh frame's unapplied row never
    for k in (0, 1, len(want) // 2, len(want) - 1):
        before, control, after = want[k]
        assert torch.equal(got["state"][k], before)
        assert torch.equal(got["control"][k], control)
        assert torch.equal(got["next/state"][k], after)
    # an epoch of the loader delivers each of them once
    seen = torch.cat([b["next/state"] for b in pairs.loader(37, seed=1)])
    assert len(seen) == len(want)
    key = lambda rows: sorted(map(tuple, rows.tolist()))  # noqa: E731
    assert key(seen) == key(got["next/state"])


def test_regenerate_reproduces_a_trajectory_with_its_resets(store):
    i = next(i for i in range(len(store)) if store[i]["first"].sum() >= 2)
    again = store.regenerate(dataset(), i)
    for key in store[i]:
        torch.testing.assert_close(again[key], store[i][key], rtol=0, atol=0, equal_nan=True)


def test_minari_splits_a_trajectory_into_its_episodes(tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    pytest.importorskip("h5py")
    ds = dataset()
    simloader.write(ds, tmp_path / "cartpole-episodes-v0", batches=1, format="minari",
                    progress=False)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    loaded = list(minari.load_dataset("cartpole-episodes-v0").iterate_episodes())
    batch = next(iter(ds))
    want = []
    for row in range(NBATCH):
        first = batch["first"][row].numpy()
        starts = [0] + list(np.flatnonzero(first))
        for k, start in enumerate(starts):
            stop = starts[k + 1] if k + 1 < len(starts) else NSTEP
            if k == 0:
                obs = np.concatenate([batch["initial_state"][row][None].numpy(),
                                      batch["state"][row, :stop].numpy()])
                act = batch["control"][row, :stop].numpy()
            else:
                obs = batch["state"][row, start:stop].numpy()
                act = batch["control"][row, start + 1:stop].numpy()
            if len(act):
                want.append((obs, act, bool(batch["terminated"][row, stop - 1])))
    assert len(loaded) == len(want) > NBATCH
    for episode, (obs, act, terminal) in zip(loaded, want):
        np.testing.assert_array_equal(episode.observations, obs)
        np.testing.assert_array_equal(episode.actions, act)
        assert bool(episode.terminations[-1]) == terminal
        assert bool(episode.truncations[-1]) == (not terminal)
        assert not episode.terminations[:-1].any() and not episode.truncations[:-1].any()
