"""A store's writer touches nothing that is not its own, a store is read while it is written
or grown, and nothing missing or edited goes unnoticed (zarr stores, CPU backend)."""

import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import simloader
from simloader.store import lock
from simloader.store.zarr_format import DamagedStore

zarr = pytest.importorskip("zarr")


def tiny(**kwargs):
    base = dict(backend="cpu", nbatch=2, nstep=5, nthread=1, seed=3,
                record=("state", "sensordata"), control=simloader.controls.Uniform())
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


def files_of(folder):
    """Every file below `folder` with its bytes."""
    out = {}
    for directory, _, names in os.walk(folder):
        for name in names:
            path = os.path.join(directory, name)
            out[os.path.relpath(path, folder)] = open(path, "rb").read()
    return out


def project(folder):
    """A user's project: what no store writer may touch."""
    os.makedirs(folder / "src")
    (folder / "src" / "train.py").write_text("print('train')\n")
    (folder / "notes.txt").write_text("notes\n")
    os.makedirs(folder / "downloads")
    (folder / "downloads" / "weights.bin.partial").write_bytes(b"half a download")
    return files_of(folder)


# --------------------------------------------------------------------------- not its own

@pytest.mark.parametrize("replace", [False, True])
def test_a_folder_that_is_not_a_store_is_refused_and_kept(tmp_path, replace):
    folder = tmp_path / "myproject"
    before = project(folder)
    with pytest.raises(ValueError, match=r"myproject' is a folder that is not a simloader "
                                         r"store \(it holds 'downloads', 'notes.txt', 'src'\)"):
        simloader.write(tiny(), folder, batches=1, progress=False, replace=replace)
    assert files_of(folder) == before  # nothing deleted, nothing written (not even a lock)


def test_system_folders_are_refused_at_once(tmp_path, monkeypatch):
    """Refused before the lock is taken: should the refusal ever go, the guard below fails
    the test instead of letting a writer loose on the system (as root, an unguarded run of
    the code before the refusal wrote `/zarr.json` and walked the whole disk)."""
    from simloader import cli
    from simloader.store import ownership

    def reached(self):
        raise AssertionError(f"write reached the lock of {self.root!r}")
    monkeypatch.setattr(lock.WriterLock, "acquire", reached)
    monkeypatch.setattr(ownership, "clear", lambda root: reached(lock.WriterLock(root, "")))
    before = set(os.listdir("/"))
    with pytest.raises(ValueError, match=r"path: '/' is a system folder"):
        simloader.write(tiny(), "/", batches=1, progress=False)
    with pytest.raises(ValueError, match=r"system folder"):
        simloader.write(tiny(), "/usr/../usr/", batches=1, progress=False, replace=True)
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))  # the home folder itself, empty or not
    with pytest.raises(ValueError, match=r"system folder"):
        simloader.write(tiny(), str(home), batches=1, progress=False)
    with pytest.raises(SystemExit) as exited:
        cli.main(["write", "cartpole", "--out", "/", "--batches", "1", "--nbatch", "2",
                  "--nstep", "3", "--backend", "cpu"])
    assert exited.value.code not in (0, None)
    assert set(os.listdir("/")) == before and os.listdir(home) == []


def test_a_file_path_is_refused(tmp_path):
    file = tmp_path / "data.npz"
    file.write_bytes(b"mine")
    with pytest.raises(ValueError, match=r"data.npz' is a file, not a folder"):
        simloader.write(tiny(), file, batches=1, progress=False, replace=True)
    assert file.read_bytes() == b"mine"


def test_replace_removes_the_store_only_and_a_killed_creation_is_taken_over(tmp_path):
    path = simloader.write(tiny(), tmp_path / "s.zarr", batches=2, progress=False)
    (tmp_path / "s.zarr" / "README.txt").write_text("what this store is")
    with pytest.raises(ValueError, match=r"holds another configuration"):
        simloader.write(tiny(seed=4), path, batches=2, progress=False)
    try:
        simloader.write(tiny(seed=4), path, batches=2, progress=False)
    except ValueError as e:
        assert not str(e).startswith("path:")  # a store's content, not a bad argument
    simloader.write(tiny(seed=4), path, batches=2, progress=False, replace=True)
    assert (tmp_path / "s.zarr" / "README.txt").read_text() == "what this store is"
    assert len(simloader.StoredDataset(path)) == 4
    # what a creation killed before its root leaves: the lock and the slots' array
    killed = tmp_path / "k.zarr"
    os.makedirs(killed / "provenance" / "written")
    (killed / "simloader.lock").write_text("")
    (killed / "provenance" / "zarr.json").write_text("{}")
    simloader.write(tiny(), killed, batches=1, progress=False)
    assert len(simloader.StoredDataset(killed)) == 2


def test_only_the_writers_own_leftovers_are_removed(tmp_path):
    path = simloader.write(tiny(), tmp_path / "p.zarr", batches=1, progress=False)
    mine = os.path.join(path, "state", "c", "0", "0", f"0.{'ab' * 16}.partial")
    theirs = os.path.join(path, "state", "c", "0", "0", "0.download.partial")
    for f in (mine, theirs):
        open(f, "wb").close()
    simloader.write(tiny(), path, batches=2, progress=False)
    assert not os.path.exists(mine) and os.path.exists(theirs)


# --------------------------------------------------------------------------- links

def test_a_linked_lock_is_refused_and_its_target_kept(tmp_path):
    path = simloader.write(tiny(), tmp_path / "l.zarr", batches=1, progress=False)
    outside = tmp_path / "precious.txt"
    outside.write_text("do not empty me")
    os.unlink(os.path.join(path, "simloader.lock"))
    os.symlink(outside, os.path.join(path, "simloader.lock"))
    with pytest.raises(ValueError, match=r"holds links \('simloader.lock'\)"):
        simloader.write(tiny(), path, batches=2, progress=False)
    with pytest.raises(ValueError, match=r"simloader.lock is a link"):
        lock.WriterLock(path, lock.new_job_id()).acquire()
    assert outside.read_text() == "do not empty me"


def test_a_linked_folder_inside_a_store_is_refused_before_anything_is_written(tmp_path):
    path = simloader.write(tiny(), tmp_path / "w.zarr", batches=1, progress=False)
    written = os.path.join(path, "provenance", "written")
    outside = tmp_path / "elsewhere"
    shutil.move(written, outside)
    os.symlink(outside, written)
    before = files_of(outside)
    lock_before = open(os.path.join(path, "simloader.lock"), "rb").read()
    with pytest.raises(ValueError, match=r"holds links \('provenance/written'\)"):
        simloader.write(tiny(), path, batches=3, progress=False)
    with pytest.raises(DamagedStore, match=r"holds links"):
        simloader.StoredDataset(path)
    assert files_of(outside) == before
    assert open(os.path.join(path, "simloader.lock"), "rb").read() == lock_before


# --------------------------------------------------------------------------- read while written

GROW = """
import sys, simloader
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=5, nthread=1, seed=3,
                          record=("state", "sensordata"), control=simloader.controls.Uniform())
for batches in map(int, sys.argv[2:]):
    simloader.write(ds, sys.argv[1], batches=batches, progress=False)
"""


def test_a_store_is_read_while_it_grows_and_never_called_damaged(tmp_path):
    path = str(tmp_path / "g.zarr")
    simloader.write(tiny(), path, batches=10, progress=False)
    writer = subprocess.Popen([sys.executable, "-c", GROW, path, "40", "80", "120"])
    opens, refusals, sizes = 0, [], []
    try:
        while writer.poll() is None:
            try:
                stored = simloader.StoredDataset(path)
                sizes.append(len(stored))
                stored[len(stored) - 1]  # the newest committed trajectory reads
            except DamagedStore as e:
                refusals.append(str(e))
            opens += 1
    finally:
        writer.wait(timeout=300)
    assert writer.returncode == 0
    assert opens >= 20, opens
    assert refusals == [], f"{len(refusals)} of {opens} opens refused: {refusals[0]}"
    assert sizes == sorted(sizes)  # each open sees one moment, never fewer than before
    assert len(simloader.StoredDataset(path, verify=True)) == 240


# --------------------------------------------------------------------------- nothing missing

def clean_store(tmp_path, name="clean.zarr", **kwargs):
    return zarr.open_group(simloader.write(tiny(**kwargs), tmp_path / name, batches=3,
                                           progress=False), mode="r")


def same_as(path, clean):
    got = zarr.open_group(path, mode="r")
    for key in ("state", "control", "diverged", "sensordata", "initial_state"):
        assert np.array_equal(got[key][...], clean[key][...], equal_nan=True), key


def test_a_removed_array_is_named_and_restored_by_writing_again(tmp_path):
    ds = tiny(control=simloader.controls.Uniform(), nbatch=3)
    clean = clean_store(tmp_path, nbatch=3)
    path = simloader.write(ds, tmp_path / "r.zarr", batches=3, progress=False)
    shutil.rmtree(os.path.join(path, "diverged"))
    with pytest.raises(DamagedStore, match=r"diverged/zarr.json: missing: the store's array "
                                           r"'diverged'"):
        simloader.StoredDataset(path, verify=True)
    simloader.write(ds, path, batches=3, progress=False)
    stored = simloader.StoredDataset(path, verify=True)
    same_as(path, clean)
    assert len(stored.transitions()) == len(simloader.StoredDataset(clean.store.root)
                                            .transitions())
    # the metadata alone: the files are there, the store cannot read them
    os.unlink(os.path.join(path, "state", "zarr.json"))
    with pytest.raises(DamagedStore, match=r"state/zarr.json: missing"):
        simloader.StoredDataset(path)
    simloader.write(ds, path, batches=3, progress=False)
    same_as(path, clean)
    # the checksums' record itself: every committed slot is redone
    os.unlink(os.path.join(path, "provenance", "checksum", "zarr.json"))
    with pytest.raises(DamagedStore, match=r"checksum/zarr.json: missing"):
        simloader.StoredDataset(path)
    simloader.write(ds, path, batches=3, progress=False)
    simloader.StoredDataset(path, verify=True)
    same_as(path, clean)


def test_edited_dtypes_and_shapes_are_refused_and_restored(tmp_path):
    path = simloader.write(tiny(), tmp_path / "e.zarr", batches=2, progress=False)
    clean = zarr.open_group(simloader.write(tiny(), tmp_path / "c.zarr", batches=2,
                                            progress=False), mode="r")
    meta_file = os.path.join(path, "sensordata", "zarr.json")
    original = json.load(open(meta_file))
    relabelled = {**original, "data_type": "int64"}
    json.dump(relabelled, open(meta_file, "w"))
    with pytest.raises(DamagedStore, match=r"sensordata/zarr.json: edited: data_type 'int64', "
                                           r"written as 'float64'"):
        simloader.StoredDataset(path)
    # a consistent swap of the trailing sides (shape, shard and chunk alike)
    swapped = json.loads(json.dumps(original))
    n, a, b = swapped["shape"]
    swapped["shape"] = [n, b, a]
    grid = swapped["chunk_grid"]["configuration"]["chunk_shape"]
    grid[1], grid[2] = grid[2], grid[1]
    inner = swapped["codecs"][0]["configuration"]["chunk_shape"]
    inner[1], inner[2] = inner[2], inner[1]
    json.dump(swapped, open(meta_file, "w"))
    with pytest.raises(DamagedStore, match=rf"edited: trailing shape \[{b}, {a}\], written as "
                                           rf"\[{a}, {b}\]"):
        simloader.StoredDataset(path)
    simloader.write(tiny(), path, batches=2, progress=False)  # restored from the record
    assert json.load(open(meta_file)) == original
    same_as(path, clean)


# --------------------------------------------------------------------------- who writes

@pytest.mark.parametrize("rank, world, match", [
    ("0", "2", r"RANK=0 and WORLD_SIZE=2 are set, but no torch.distributed process group"),
    ("1", "2", r"RANK=1 and WORLD_SIZE=2 are set, but no torch.distributed process group"),
    ("2", "2", r"RANK: expected an int in \[0, WORLD_SIZE=2\), got 2"),
    ("0", "0", r"WORLD_SIZE: expected an int >= 1 \(the number of ranks\), got 0"),
    ("0", "-3", r"WORLD_SIZE: expected an int >= 1 \(the number of ranks\), got -3"),
    ("x", "2", r"RANK: expected an int .*got 'x'"),
])
def test_ranks_without_a_process_group_are_refused_before_writing(tmp_path, monkeypatch,
                                                                   rank, world, match):
    monkeypatch.setenv("RANK", rank)
    monkeypatch.setenv("WORLD_SIZE", world)
    with pytest.raises(ValueError, match=match):
        simloader.write(tiny(), tmp_path / "r.zarr", batches=4, progress=False)
    assert not os.path.exists(tmp_path / "r.zarr")


def test_a_job_id_is_new_for_every_job():
    assert len({lock.new_job_id() for _ in range(100)}) == 100


def test_continued_episodes_resume_only_with_their_number_of_workers(tmp_path):
    def continued():
        return tiny(continue_episodes=True, nbatch=2, nstep=4)
    path = simloader.write(continued(), tmp_path / "c.zarr", batches=4, num_workers=2,
                           progress=False)
    with pytest.raises(ValueError, match=r"written by 2 DataLoader worker\(s\).*with "
                                         r"num_workers=2, not 1 worker"):
        simloader.write(continued(), path, batches=6, progress=False)
    whole = simloader.write(continued(), tmp_path / "w.zarr", batches=6, num_workers=2,
                            progress=False)
    simloader.write(continued(), path, batches=6, num_workers=2, progress=False)
    a, b = zarr.open_group(path, mode="r"), zarr.open_group(whole, mode="r")
    assert np.array_equal(a["state"][...], b["state"][...])
    # a stream that does not continue may change its number of workers
    plain = simloader.write(tiny(), tmp_path / "p.zarr", batches=2, num_workers=2,
                            progress=False)
    simloader.write(tiny(), plain, batches=3, progress=False)
    assert torch.equal(simloader.StoredDataset(plain)[5]["state"],
                       torch.from_numpy(clean_store(tmp_path)["state"][5]))
