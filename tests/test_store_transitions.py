"""StoredDataset.transitions: per-trajectory values carried by each transition (`context=`),
per-frame keys told apart from per-trajectory ones by the store's frame axis, a loader that
resumes mid-epoch bit for bit (workers included), and clear refusals of what is not a store
or has nothing committed yet."""

import errno
import glob
import itertools
import json
import os

import numpy as np
import pytest
import torch

import simloader
from simloader.store import order as orders, pipeline, transitions, zarr_format as store_format

pytest.importorskip("zarr")


def cartpole(**kwargs):
    """nstep=5 frames and cartpole's nstate=5: `initial_state` (ntrajectories x nstate) is as
    wide as the frame axis, and must still not pass for a per-frame key."""
    base = dict(backend="cpu", nbatch=3, nstep=5, nthread=1, seed=3,
                control=simloader.controls.Uniform(), record=("state", "qpos"),
                randomize=[simloader.randomize.scale("body_mass",
                                                     simloader.randomize.Uniform(0.5, 2.0),
                                                     on="pole")])
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    return simloader.write(cartpole(), tmp_path_factory.mktemp("t") / "s.zarr", batches=4,
                           progress=False)


MASS = "params/body_mass[pole]"


def test_per_trajectory_values_come_with_each_transition_as_context(store):
    stored = simloader.StoredDataset(store)
    transitions = stored.transitions(state="state", context=("params", "initial_state"))
    assert len(transitions) == 12 * 5
    for k in (0, 4, 5, 33, 59):  # trajectory k // 5
        item, trajectory = transitions[k], stored[k // 5]
        assert torch.equal(item[MASS], trajectory["params"]["body_mass[pole]"])
        assert torch.equal(item["initial_state"], trajectory["initial_state"])
    # in a loader's batches too, each row its own trajectory's value
    masses = torch.stack([stored[i]["params"]["body_mass[pole]"] for i in range(12)])
    finals = {tuple(stored[i]["state"][-1].tolist()): i for i in range(12)}
    seen = 0
    for batch in transitions.loader(7, order="quasi_random", seed=1):
        assert batch[MASS].shape == (len(batch["state"]), 1)
        for next_state, mass in zip(batch["next/state"], batch[MASS]):
            if tuple(next_state.tolist()) in finals:  # a trajectory's last transition
                assert torch.equal(mass, masses[finals[tuple(next_state.tolist())]])
                seen += 1
    assert seen == 12
    # other state keys start at frame 1: the trajectory's value still follows them
    qpos = stored.transitions("qpos", context=MASS)
    assert len(qpos) == 12 * 4 and torch.equal(qpos[4 * 7][MASS], masses[7])


def test_per_trajectory_keys_are_refused_as_states_and_point_to_context(store):
    stored = simloader.StoredDataset(store)
    with pytest.raises(KeyError, match=r"state: 'params/body_mass\[pole\]' is per-trajectory "
                                       r".*pass it as context=\("):
        stored.transitions(state=("state", MASS))
    # as wide as the frame axis (nstate == nframes == 5), yet one value per trajectory
    with pytest.raises(KeyError, match="state: 'initial_state' is per-trajectory"):
        stored.transitions(state="initial_state")
    with pytest.raises(KeyError, match="state: 'control' is every transition's action"):
        stored.transitions(state="control")
    with pytest.raises(KeyError) as wrong:
        stored.transitions(state="qpso")
    said = str(wrong.value)
    assert "did you mean 'qpos'" in said and "per-frame keys: ['qpos', 'state']" in said
    assert "initial_state" not in said and "params/" not in said
    with pytest.raises(KeyError, match="context: 'qpos' is per-frame: pass it in state="):
        stored.transitions(context="qpos")
    with pytest.raises(KeyError, match="context: 'mass' is not a per-trajectory key"):
        stored.transitions(context="mass")


def test_context_follows_the_trajectories_kept_when_diverged_ones_are_dropped(tmp_path):
    control = np.zeros((3, 5, 1))
    control[1, 2] = np.inf  # row 1 of every batch diverges
    path = simloader.write(cartpole(control=control), tmp_path / "d.zarr", batches=2,
                           progress=False)
    stored = simloader.StoredDataset(path)
    kept = stored.transitions(context=("diverged", MASS))
    assert len(kept) == 4 * 5
    for k, trajectory in zip((0, 5, 10, 15), (0, 2, 3, 5)):
        assert torch.equal(kept[k]["state"], stored[trajectory]["initial_state"])
        assert torch.equal(kept[k][MASS], stored[trajectory]["params"]["body_mass[pole]"])
        assert kept[k]["diverged"].item() is False
    every = stored.transitions(diverged="keep", context="diverged")
    assert every.gather(np.arange(30))["diverged"].tolist() == \
        ([False] * 5 + [True] * 5 + [False] * 5) * 2


def test_a_gather_never_clips_an_index_out_of_range():
    rows, out = np.arange(6.0).reshape(3, 2), np.empty((2, 2))
    transitions._take(rows, np.array([0, 2]), out)
    assert out.tolist() == [[0, 1], [4, 5]]
    with pytest.raises(IndexError, match="row 3 of a shard of 3 rows"):
        transitions._take(rows, np.array([0, 3]), out)


def batches(loader, epochs=1, first=None):
    """The batches of `epochs` iterations, or the first `first` batches of one."""
    if first is not None:
        return list(itertools.islice(loader, first))  # asks for no batch beyond them
    return [batch for _ in range(epochs) for batch in loader]


def same(a, b):
    return len(a) == len(b) and all(
        x.keys() == y.keys() and all(x[k].dtype == y[k].dtype and torch.equal(x[k], y[k])
                                     for k in x) for x, y in zip(a, b))


@pytest.mark.parametrize("order, num_workers", [("quasi_random", 0), ("quasi_random", 2),
                                                ("random", 2)])
def test_the_loader_resumes_mid_epoch_and_across_epochs_bit_for_bit(store, order,
                                                                    num_workers):
    pytest.importorskip("torchdata")

    def loader(seed):  # new Python objects each time: the store opened anew
        transitions = simloader.StoredDataset(store).transitions()
        return transitions.loader(7, order=order, seed=seed, num_workers=num_workers,
                                  multiprocessing_context="fork" if num_workers else None)

    whole = batches(loader(11), epochs=3)  # 9 batches an epoch: 60 transitions by 7
    assert len(whole) == 27 and not same(whole[:9], whole[9:18])  # a new order each epoch
    for done in (4, 9, 13):  # mid-epoch 0, at its end, mid-epoch 1
        first = loader(11)
        taken = batches(first, epochs=done // 9) + batches(first, first=done % 9) \
            if done % 9 else batches(first, epochs=done // 9)
        state = json.loads(json.dumps(first.state_dict()))  # as a checkpoint keeps it
        resumed = loader(None)  # the seed comes with the state
        resumed.load_state_dict(state)
        rest = batches(resumed, epochs=3 - done // 9)
        assert same(taken, whole[:done]) and same(rest, whole[done:]), done


def test_a_block_order_resumes_where_its_state_says():
    make = lambda batch_size=8, seed=None: orders.BlockOrder(50, batch_size, "quasi_random",
                                                             block=10, window=2, seed=seed)
    sampler = make(seed=4)
    whole = [b.tolist() for _ in range(2) for b in sampler]  # 2 epochs of 7 batches
    started = make(seed=4)
    it = iter(started)
    head = [next(it).tolist() for _ in range(3)]
    state = started.state_dict()
    assert (state["epoch"], state["position"], state["seed"]) == (0, 3, 4)
    again = make()
    again.load_state_dict(state)
    assert head + [b.tolist() for _ in range(2) for b in again] == whole
    rest = list(it)  # to the epoch's end: resumed there, the epoch's rest is empty
    again = make()
    again.load_state_dict(started.state_dict())
    assert [list(again), [b.tolist() for b in again]] == [[], whole[7:]] and len(rest) == 4
    with pytest.raises(ValueError, match=r"state: saved by another order of batches "
                                         r"\(batch_size: saved 8, now 16\)"):
        make(batch_size=16).load_state_dict(state)


def test_a_file_or_a_missing_path_is_refused_by_name(tmp_path):
    file = tmp_path / "notes.txt"
    file.write_text("not a store")
    with pytest.raises(ValueError, match=r"path: '.*notes.txt' is a file, not a store folder"):
        simloader.StoredDataset(file)
    with pytest.raises(ValueError, match=r"path: '.*absent.zarr' does not exist"):
        simloader.StoredDataset(tmp_path / "absent.zarr")


@pytest.mark.parametrize("how", ["marks removed", "writer stopped in its first batch"])
def test_transitions_of_a_store_without_a_committed_slot_say_so(tmp_path, monkeypatch, how):
    path = str(tmp_path / "e.zarr")
    if how == "marks removed":
        simloader.write(cartpole(), path, batches=2, progress=False)
        for mark in glob.glob(os.path.join(path, store_format.WRITTEN.name, "c", "*")):
            os.unlink(mark)
    else:
        from simloader.store.folder import StoreFolder
        real = StoreFolder.stage

        def full(folder, name, parts):  # every slot's (slot 1 commits beside slot 0)
            if "/c/" in name:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), folder.where(name))
            return real(folder, name, parts)

        monkeypatch.setattr(StoreFolder, "stage", full)
        with pytest.raises(OSError):
            simloader.write(cartpole(), path, batches=2, progress=False)
    stored = simloader.StoredDataset(path)  # readable: nothing in it yet
    assert len(stored) == 0
    with pytest.raises(ValueError, match=r"transitions: the store at '.*e.zarr' has no "
                                         r"committed batch slot yet \(none of its 2 slot"):
        stored.transitions()
