"""A `Mixture` written to a store and read back (`simloader.store.mixture_store`, CPU engine):
each task's store holds exactly the batches the mixture delivered for it, items and
transitions carry `task` (padded with masks across tasks of other widths), `regenerate` works
per trajectory, a larger `batches` extends it, another mixture is refused."""

import os

import numpy as np
import pytest
import torch

import simloader
from simloader.store import mixture_store

pytest.importorskip("zarr")


def member(model, nbatch, **kwargs):
    return simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=6, nthread=1,
                                seed=2, control=simloader.controls.Uniform(), **kwargs)


def mixture(**kwargs):
    return simloader.Mixture({"cartpole": member("cartpole", 4),
                              "humanoid": member("humanoid", 2)}, **kwargs)


def test_a_written_mixture_holds_the_batches_the_mixture_delivered(tmp_path):
    mix = mixture(weights=[1, 2], seed=3)
    path = simloader.write(mix, tmp_path / "m.zarr", batches=8, progress=False)
    stored = simloader.open_store(path)
    assert isinstance(stored, mixture_store.StoredMixture)
    # one explicit opener picks the kind; StoredDataset opens one stream's store only
    assert "__new__" not in vars(simloader.StoredDataset)
    with pytest.raises(ValueError, match=r"holds a mixture's store .* simloader.open_store"):
        simloader.StoredDataset(path)
    task = simloader.open_store(os.path.join(path, "tasks", "cartpole"))
    assert type(task) is simloader.StoredDataset and len(task) == len(stored.tasks["cartpole"])
    delivered = {0: [], 1: []}
    for _, batch in zip(range(8), mixture(weights=[1, 2], seed=3)):
        delivered[int(batch["task"])].append(batch)
    assert stored.info["counts"] == [len(delivered[0]), len(delivered[1])]
    assert 0 < len(delivered[0]) < 8  # both tasks drawn
    assert len(stored) == 4 * len(delivered[0]) + 2 * len(delivered[1])
    i = 0
    for task, name in enumerate(("cartpole", "humanoid")):
        for batch in delivered[task]:
            for row in range(len(batch["state"])):
                item = stored[i]
                assert int(item["task"]) == task
                for key in ("state", "control", "sensordata", "initial_state"):
                    assert torch.equal(item[key], batch[key][row]), (name, key)
                i += 1
    assert i == len(stored)
    # each trajectory regenerates from its member, bit for bit
    again = stored.regenerate(mixture(weights=[1, 2], seed=3), len(stored) - 1)
    assert torch.equal(again["state"], stored[len(stored) - 1]["state"])
    assert int(again["task"]) == 1
    assert "humanoid" in stored.describe() and "cartpole" in stored.describe()


def test_transitions_mix_the_tasks_padded_with_masks(tmp_path):
    path = simloader.write(mixture(seed=1), tmp_path / "t.zarr", batches=6, progress=False)
    stored = simloader.open_store(path)
    transitions = stored.transitions()
    parts = [stored.tasks[n].transitions() for n in ("cartpole", "humanoid")]
    assert len(transitions) == sum(len(p) for p in parts)
    ks = np.arange(0, len(transitions), 5)
    batch = transitions.gather(ks)
    assert batch["state"].shape == (len(ks), 56) and batch["control"].shape == (len(ks), 21)
    cart = batch["task"] == 0
    assert cart.any() and (~cart).any()
    # a cart-pole row: its 5 state columns real, the rest zero and masked out
    assert batch["mask/state"][cart][:, :5].all() and not batch["mask/state"][cart][:, 5:].any()
    assert not batch["state"][cart][:, 5:].any() and batch["mask/state"][~cart].all()
    first = parts[0].gather(ks[ks < len(parts[0])])
    assert torch.equal(batch["state"][cart][:, :5], first["state"])
    # any order, negative indices, as Transitions.gather
    mixed = transitions.gather([len(parts[0]), 0, -1])
    assert mixed["task"].tolist() == [1, 0, 1]
    assert torch.equal(mixed["state"][1, :5], parts[0].gather([0])["state"][0])
    assert torch.equal(mixed["state"][2], parts[1].gather([len(parts[1]) - 1])["state"][0])
    with pytest.raises(IndexError, match="out of range"):
        transitions.gather([len(transitions)])
    assert torch.equal(batch["next/state"][cart][:, :5], first["next/state"])
    loader = transitions.loader(32, order="random", seed=0)
    batches = list(loader)
    assert sum(len(b["task"]) for b in batches) == len(transitions)
    # a store of an unpadded mixture: one task per batch, both tasks in the epoch, every
    # transition once, the same keys and widths in every batch
    assert all(len(set(b["task"].tolist())) == 1 for b in batches)
    assert {int(b["task"][0]) for b in batches} == {0, 1}
    assert all(set(b) == set(batch) and b["state"].shape[1] == 56 for b in batches)
    rows = torch.cat([torch.cat([b["task"][:, None].double(), b["state"], b["next/state"]], 1)
                      for b in batches])
    assert len(torch.unique(rows, dim=0)) == len(transitions)
    again = [b["state"] for b in transitions.loader(32, order="random", seed=0)]
    assert all(torch.equal(a, b["state"]) for a, b in zip(again, batches))
    # a batch of one task's rows has the keys and widths of any other
    alone = transitions.gather(np.arange(3))
    assert (alone["task"] == 0).all() and alone["state"].shape == (3, 56)
    assert set(alone) == set(batch)


def test_a_padded_mixtures_store_pads_its_items(tmp_path):
    path = simloader.write(mixture(pad=True), tmp_path / "p.zarr", batches=2, progress=False)
    stored = simloader.open_store(path)
    assert stored.pad
    items = [stored[i] for i in range(len(stored))]
    assert {tuple(it["state"].shape) for it in items} == {(6, 56)}
    cart = [it for it in items if int(it["task"]) == 0]
    # masks per row, as the mixture's (no frame axis)
    assert cart and cart[0]["mask/state"].shape == (56,)
    assert not cart[0]["mask/state"][5:].any() and cart[0]["mask/state"][:5].all()
    streamed = next(iter(mixture(pad=True)))
    assert streamed["mask/state"].shape[1:] == cart[0]["mask/state"].shape
    # keys= keeps to the keys asked for
    only = simloader.open_store(path, keys=["control"])[0]
    assert set(only) == {"control", "mask/control", "task"}
    batch = torch.utils.data.default_collate(items)  # one DataLoader batch of both tasks
    assert batch["state"].shape == (len(items), 6, 56)


def test_writing_again_extends_and_another_mixture_is_refused(tmp_path):
    path = str(tmp_path / "e.zarr")
    simloader.write(mixture(seed=4), path, batches=3, progress=False)
    small = len(simloader.open_store(path))
    simloader.write(mixture(seed=4), path, batches=7, progress=False)
    big = simloader.open_store(path)
    counts = mixture_store.counts(mixture(seed=4), 7)
    assert big.info["counts"] == counts and len(big) == 4 * counts[0] + 2 * counts[1] > small
    with pytest.raises(ValueError, match=r"another mixture.*seed: stored 4, given 5"):
        simloader.write(mixture(seed=5), path, batches=7, progress=False)
    # a member of another configuration is refused before anything is written
    reseeded = simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=6, nthread=1,
                                    seed=9, control=simloader.controls.Uniform())
    other = simloader.Mixture({"cartpole": reseeded,
                               "humanoid": member("humanoid", 2)}, seed=4)
    root = open(os.path.join(path, "zarr.json")).read()
    with pytest.raises(ValueError, match=r"task 'cartpole'.*seed: stored 2, given 9"):
        simloader.write(other, path, batches=20, progress=False)
    assert open(os.path.join(path, "zarr.json")).read() == root
    with pytest.raises(ValueError, match=r"not a mixture's|holds one dataset's batches"):
        simloader.write(mixture(seed=4), simloader.write(
            member("cartpole", 4), tmp_path / "one.zarr", batches=1, progress=False),
            batches=1, progress=False)
    with pytest.raises(ValueError, match=r"format='minari'.*a Mixture is written as a zarr"):
        simloader.write(mixture(), tmp_path / "x-v0", batches=1, format="minari")
    assert os.path.isdir(os.path.join(path, "tasks", "humanoid"))


def test_a_mixture_stores_transitions_loader_resumes_mid_epoch(tmp_path):
    pytest.importorskip("torchdata")
    path = simloader.write(mixture(seed=2), tmp_path / "r.zarr", batches=6, progress=False)
    transitions = simloader.open_store(path).transitions()
    loader = transitions.loader(16, seed=5)
    it = iter(loader)
    for _ in range(3):
        next(it)
    state = loader.state_dict()
    rest = [b["state"] for b in it]
    resumed = transitions.loader(16, seed=5)
    resumed.load_state_dict(state)
    again = [b["state"] for b in resumed]
    assert len(again) == len(rest) > 0
    assert all(torch.equal(a, b) for a, b in zip(again, rest))


def test_simloader_info_says_what_each_tasks_columns_mean(tmp_path, capsys):
    from simloader import cli
    path = simloader.write(mixture(pad=True), tmp_path / "i.zarr", batches=1, progress=False)
    cli.main(["info", path])
    said = capsys.readouterr().out
    assert "task 0 'cartpole'" in said and "task 1 'humanoid'" in said
    assert "mask/state" in said  # the padded columns of each task
    one = simloader.write(member("cartpole", 4), tmp_path / "one.zarr", batches=1,
                          progress=False)
    cli.main(["info", one])
    assert "(4 trajectories)" in capsys.readouterr().out


def test_a_link_under_tasks_is_refused_and_what_it_points_to_untouched(tmp_path):
    path = simloader.write(mixture(seed=4), tmp_path / "l.zarr", batches=6, progress=False)
    outside = tmp_path / "precious"
    outside.mkdir()
    (outside / "notes.txt").write_text("mine")
    task = os.path.join(path, "tasks", sorted(os.listdir(os.path.join(path, "tasks")))[0])
    assert os.path.isdir(task) and not task.endswith("zarr.json")
    import shutil
    shutil.rmtree(task)
    os.symlink(outside, task)
    with pytest.raises(ValueError, match=r"holds links under tasks/"):
        simloader.write(mixture(seed=4), path, batches=4, progress=False)
    with pytest.raises(ValueError, match=r"holds links under tasks/"):
        simloader.write(mixture(seed=4), path, batches=4, progress=False, replace=True)
    assert os.listdir(outside) == ["notes.txt"] and (outside / "notes.txt").read_text() == "mine"
