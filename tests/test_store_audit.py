"""What the third store audit found, held: a reader never mixes two stores, no store is made
inside another, a mixture store knows its members, hostile or unlucky stores and paths are
refused by name, and a store of a small model is not mostly its model file (CPU engine)."""

import json
import os
import shutil
import threading

import pytest
import torch

import simloader
from simloader.store.shards import StoreReplaced
from simloader.store.zarr_format import DamagedStore

zarr = pytest.importorskip("zarr")

from test_store_safety import files_of, tiny  # noqa: E402


# --------------------------------------------------------------------------- one store per reader

def test_a_reader_opened_before_a_replace_refuses_instead_of_mixing(tmp_path):
    path = str(tmp_path / "r.zarr")
    simloader.write(tiny(seed=1), path, batches=6, progress=False)
    reader = simloader.StoredDataset(path)
    old = [reader[i]["state"].clone() for i in range(4)]  # slots 0 and 1 read (and open)
    simloader.write(tiny(seed=2), path, batches=6, progress=False, replace=True)
    assert all(torch.equal(reader[i]["state"], old[i]) for i in range(4))  # the opened maps
    with pytest.raises(StoreReplaced, match=r"was replaced by another store .* since it was "
                                            r"opened.* Open it again"):
        reader[10]  # slot 5: never opened by this reader
    fresh = simloader.StoredDataset(path)
    assert not torch.equal(fresh[10]["state"], simloader.StoredDataset(path)[0]["state"])


def test_a_reader_of_a_removed_store_says_it_was_removed(tmp_path):
    path = str(tmp_path / "g.zarr")
    simloader.write(tiny(), path, batches=2, progress=False)
    reader = simloader.StoredDataset(path)
    shutil.rmtree(path)
    os.makedirs(path)
    with pytest.raises(StoreReplaced, match=r"was removed since it was opened"):
        reader[0]


def test_a_growing_store_keeps_its_identity_for_its_readers(tmp_path):
    path = str(tmp_path / "grow.zarr")
    simloader.write(tiny(), path, batches=2, progress=False)
    reader = simloader.StoredDataset(path)
    identity = reader.info["id"]
    simloader.write(tiny(), path, batches=5, progress=False)  # the root is rewritten
    assert simloader.StoredDataset(path).info["id"] == identity
    assert len(reader[3]["state"])  # a slot it listed, opened after the growth


def test_readers_during_a_replace_get_old_items_or_a_refusal_never_new_ones(tmp_path):
    """A reader opened before reads every item while `write(replace=True)` runs beside it:
    each item is the old store's or refused; none is the new store's."""
    path = str(tmp_path / "race.zarr")
    simloader.write(tiny(seed=1), path, batches=40, progress=False)
    old = simloader.StoredDataset(path)
    want = [old[i]["state"].clone() for i in range(len(old))]
    reader = simloader.StoredDataset(path)
    writer = threading.Thread(target=simloader.write, args=(tiny(seed=2), path),
                              kwargs=dict(batches=40, progress=False, replace=True))
    outcomes = {"old": 0, "refused": 0, "other": 0}
    writer.start()
    for i in range(len(reader)):
        try:
            got = reader[i]["state"]
        except StoreReplaced:
            outcomes["refused"] += 1
            continue
        outcomes["old" if torch.equal(got, want[i]) else "other"] += 1
    writer.join()
    print(f"\nreader during a replace: {outcomes}")
    assert outcomes["other"] == 0, outcomes
    assert sum(outcomes.values()) == len(want)


# --------------------------------------------------------------------------- no store in a store

def test_a_store_inside_a_store_is_refused_naming_the_outer_one(tmp_path):
    outer = str(tmp_path / "outer.zarr")
    simloader.write(tiny(), outer, batches=1, progress=False)
    before = files_of(outer)
    for inner in (os.path.join(outer, "inner.zarr"), os.path.join(outer, "state", "x"),
                  os.path.join(outer, "a", "b", "c.zarr")):
        with pytest.raises(ValueError, match=r"lies inside the store at '.*outer.zarr'"):
            simloader.write(tiny(), inner, batches=1, progress=False)
    assert files_of(outer) == before and not os.path.exists(os.path.join(outer, "a"))
    assert len(simloader.StoredDataset(outer)) == 2


def test_a_mixtures_tasks_folder_takes_no_store_of_a_user(tmp_path):
    path = str(tmp_path / "mix.zarr")
    simloader.write(simloader.Mixture({"a": tiny(), "b": tiny(seed=4)}), path, batches=2,
                    progress=False)
    with pytest.raises(ValueError, match=r"lies inside the store at '.*mix.zarr'"):
        simloader.write(tiny(), os.path.join(path, "tasks", "c"), batches=1, progress=False)


def test_replace_keeps_a_users_zarr_group_and_a_store_beside_the_arrays(tmp_path):
    path = str(tmp_path / "keep.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    group = zarr.open_group(os.path.join(path, "mine"), mode="w")  # a user's own group
    group.create_array("values", shape=(3,), dtype="f4")[:] = [1, 2, 3]
    kept = str(tmp_path / "kept.zarr")  # a store the user moved in by hand
    simloader.write(tiny(), kept, batches=1, progress=False)
    shutil.move(kept, os.path.join(path, "kept.zarr"))
    before = {n: files_of(os.path.join(path, n)) for n in ("mine", "kept.zarr")}
    simloader.write(tiny(seed=9), path, batches=1, progress=False, replace=True)
    assert {n: files_of(os.path.join(path, n)) for n in ("mine", "kept.zarr")} == before
    assert simloader.StoredDataset(path).info["seed"] == 9


# --------------------------------------------------------------------------- a mixture's members

def test_a_mixture_member_swapped_for_another_store_is_refused(tmp_path):
    path = str(tmp_path / "mix.zarr")
    mixture = simloader.Mixture({"a": tiny(), "b": tiny(seed=4)})
    simloader.write(mixture, path, batches=6, progress=False)
    simloader.open_store(path)  # as written: read
    other = str(tmp_path / "other.zarr")
    simloader.write(tiny(seed=4), other, batches=2, progress=False)  # b's very configuration
    member = os.path.join(path, "tasks", "b")
    shutil.rmtree(member)
    shutil.copytree(other, member)
    with pytest.raises(DamagedStore, match=r"task 'b' \(tasks/b\) has identity .* but the "
                                           r"mixture recorded"):
        simloader.open_store(path)
    with pytest.raises(DamagedStore, match=r"task 'b'"):
        simloader.open_store(path, verify=True)
    with pytest.raises(ValueError, match=r"task 'b' \(tasks/b\) has identity"):
        simloader.write(mixture, path, batches=7, progress=False)


def test_a_mixture_member_of_another_configuration_is_refused_at_read(tmp_path):
    path = str(tmp_path / "mix.zarr")
    simloader.write(simloader.Mixture({"a": tiny(), "b": tiny(seed=4)}), path, batches=6,
                    progress=False)
    root = os.path.join(path, "tasks", "b", "zarr.json")
    meta = json.load(open(root))
    theirs = str(tmp_path / "theirs.zarr")
    simloader.write(tiny(seed=5, nstep=3), theirs, batches=1, progress=False)
    # another dataset's store under b's identity: its fingerprint still tells
    their_root = os.path.join(theirs, "zarr.json")
    their_meta = json.load(open(their_root))
    their_meta["attributes"]["simloader"]["id"] = meta["attributes"]["simloader"]["id"]
    json.dump(their_meta, open(their_root, "w"))
    shutil.rmtree(os.path.dirname(root))
    shutil.copytree(theirs, os.path.dirname(root))
    with pytest.raises(DamagedStore, match=r"task 'b' \(tasks/b\) has fingerprint"):
        simloader.open_store(path)


def test_a_reserved_task_name_is_refused_before_anything_is_written(tmp_path):
    path = tmp_path / "mix.zarr"
    with pytest.raises(ValueError, match=r"task name 'zarr.json' is reserved"):
        simloader.write(simloader.Mixture({"zarr.json": tiny(), "b": tiny()}), path,
                        batches=1, progress=False)
    assert not path.exists()


def test_task_names_with_slashes_are_one_folder_each_never_one_inside_another(tmp_path):
    # "params/x" once made tasks/params/x, inside task "params"'s store: refused half-made
    # in one order, a store inside a store in the other
    for names in (("params/x", "params"), ("params", "params/x"), ("camera/a/b", "camera")):
        path = tmp_path / f"mix{len(os.listdir(tmp_path))}.zarr"
        mixture = simloader.Mixture({names[0]: tiny(), names[1]: tiny(seed=4)})
        simloader.write(mixture, path, batches=4, progress=False)
        assert sorted(os.listdir(path / "tasks")) == sorted(
            n.replace("/", "%2F") for n in names + ("zarr.json",))
        read = simloader.open_store(path)
        assert len(read) == 8 and {int(read[i]["task"]) for i in range(8)} <= {0, 1}


# --------------------------------------------------------------------------- rough edges

def test_a_hard_linked_lock_is_refused_and_the_file_it_shares_kept(tmp_path):
    path = str(tmp_path / "h.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    precious = tmp_path / "precious.txt"
    precious.write_text("do not empty me")
    lock_file = os.path.join(path, "simloader.lock")
    os.unlink(lock_file)
    os.link(precious, lock_file)
    with pytest.raises(ValueError, match=r"simloader.lock has 2 hard links .* Remove"):
        simloader.write(tiny(), path, batches=2, progress=False)
    assert precious.read_text() == "do not empty me"
    os.unlink(lock_file)
    simloader.write(tiny(), path, batches=2, progress=False)  # a fresh lock: written
    copy = str(tmp_path / "copy.zarr")  # `cp -al`: both copies share every inode
    shutil.copytree(path, copy, copy_function=os.link)
    with pytest.raises(ValueError, match=r"hard links"):
        simloader.write(tiny(), copy, batches=3, progress=False)


def test_paths_no_file_can_have_are_refused_by_name(tmp_path):
    with pytest.raises(ValueError, match=r"path: .* holds a NUL character"):
        simloader.write(tiny(), str(tmp_path / "a\0b"), batches=1, progress=False)
    with pytest.raises(ValueError, match=r"path: .* holds a NUL character"):
        simloader.StoredDataset(str(tmp_path / "a\0b"))
    dangling = tmp_path / "dangling"
    os.symlink(tmp_path / "nowhere", dangling)
    with pytest.raises(ValueError, match=r"is a link to .*nowhere', which does not exist"):
        simloader.write(tiny(), dangling, batches=1, progress=False)


def test_names_too_long_and_a_dotdot_from_nowhere_are_refused_before_anything(tmp_path,
                                                                             monkeypatch):
    monkeypatch.chdir(tmp_path)
    simloader.write(tiny(), "store.zarr", batches=1, progress=False)
    before = files_of("store.zarr")
    with pytest.raises(ValueError, match=r"goes up \('..'\) from 'new', which is not a folder"):
        simloader.write(tiny(seed=8), "new/../store.zarr", batches=1, progress=False,
                        replace=True)
    with pytest.raises(ValueError, match=r"is 300 bytes, longer than the file system allows"):
        simloader.write(tiny(), "x" * 300, batches=1, progress=False)
    assert sorted(os.listdir(".")) == ["store.zarr"] and files_of("store.zarr") == before
    simloader.write(tiny(), "store.zarr/../other.zarr", batches=1, progress=False)  # fine


def test_a_path_near_the_systems_limit_is_written_whole(tmp_path, monkeypatch):
    """The store's files are reached relative to its open folder, so a store whose own path
    is close to PATH_MAX (4096) is written and read like any other."""
    deep = str(tmp_path)
    while len(deep) < 3900:
        deep = os.path.join(deep, "d" * 200)
    os.makedirs(deep)
    monkeypatch.chdir(deep)  # only relative paths work past PATH_MAX
    path = simloader.write(tiny(), "s" * 100, batches=2, progress=False)
    assert len(simloader.StoredDataset(path)) == 4


def test_a_replace_that_stops_part_way_says_so_and_a_second_replace_finishes_it(
        tmp_path, monkeypatch):
    """A replace that cannot empty one of the store's folders (read-only, seen as a non-root
    user) stops part-way: it says so (not "nothing was changed"), readers and resuming
    writers are told, and replace=True again finishes it."""
    from simloader.store.folder import StoreFolder
    from simloader.store.writer import StoreMismatch
    path = str(tmp_path / "s.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    remove_tree = StoreFolder.remove_tree

    def refused(self, name):
        if name == "state":
            raise PermissionError(13, "Permission denied", self.where(name))
        return remove_tree(self, name)

    monkeypatch.setattr(StoreFolder, "remove_tree", refused)
    with pytest.raises(OSError, match=r"the replace stopped part-way, so the store there is no "
                                      r"longer readable: write with replace=True again") as e:
        simloader.write(tiny(seed=9), path, batches=2, progress=False, replace=True)
    assert "nothing was changed" not in str(e.value)
    monkeypatch.setattr(StoreFolder, "remove_tree", remove_tree)
    with pytest.raises(DamagedStore, match=r"a replace=True of the store .* stopped part-way"):
        simloader.StoredDataset(path)
    with pytest.raises(StoreMismatch, match=r"stopped part-way .* write with replace=True"):
        simloader.write(tiny(), path, batches=1, progress=False)
    simloader.write(tiny(seed=9), path, batches=2, progress=False, replace=True)
    again = simloader.StoredDataset(path)
    fresh = next(iter(tiny(seed=9)))
    assert len(again) == 4 and torch.equal(again[0]["state"], fresh["state"][0])


def test_a_write_that_fails_before_any_store_says_none_was_written(tmp_path):
    open(tmp_path / "file", "w").close()
    os.symlink(tmp_path / "nowhere", tmp_path / "dangling")
    for parent in ("file", "dangling"):
        with pytest.raises(OSError, match=r"no store was written there") as e:
            simloader.write(tiny(), str(tmp_path / parent / "x.zarr"), batches=1,
                            progress=False)
        assert "stays readable" not in str(e.value)
    assert sorted(os.listdir(tmp_path)) == ["dangling", "file"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_folder_that_cannot_be_written_says_nothing_was_changed(tmp_path):
    path = str(tmp_path / "ro.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    os.chmod(path, 0o555)
    try:
        with pytest.raises(OSError, match=r"cannot write there; nothing was changed"):
            simloader.write(tiny(), path, batches=2, progress=False, replace=True)
    finally:
        os.chmod(path, 0o755)
    assert len(simloader.StoredDataset(path)) == 2


def test_a_store_nested_thousands_deep_is_refused_not_a_recursion_error(tmp_path):
    path = str(tmp_path / "n.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    # 1,500 levels of groups in the store's own provenance/, each made relative to the one
    # above (the full path is past PATH_MAX)
    below = os.open(os.path.join(path, "provenance"), os.O_RDONLY)
    for _ in range(1500):
        os.mkdir("g", dir_fd=below)
        deeper = os.open("g", os.O_RDONLY, dir_fd=below)
        os.close(below)
        below = deeper
        with open(os.open("zarr.json", os.O_WRONLY | os.O_CREAT, dir_fd=below), "w") as f:
            f.write('{"zarr_format": 3, "node_type": "group", "attributes": {}}')
    os.close(below)
    with pytest.raises(DamagedStore, match=r"folders nested deeper than any store"):
        simloader.StoredDataset(path)
    # removed from the bottom up (pytest's own clean-up recurses once per level)
    levels = [os.open(os.path.join(path, "provenance"), os.O_RDONLY)]
    while "g" in os.listdir(levels[-1]):
        levels.append(os.open("g", os.O_RDONLY, dir_fd=levels[-1]))
    while len(levels) > 1:
        os.unlink("zarr.json", dir_fd=levels[-1])
        os.close(levels.pop())
        os.rmdir("g", dir_fd=levels[-1])
    os.close(levels[0])


# --------------------------------------------------------------------------- the kept models

def test_the_kept_model_is_compressed_and_renders_the_same(tmp_path):
    pytest.importorskip("numcodecs")
    path = str(tmp_path / "w.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    folder = os.path.join(path, "provenance", "models")
    assert sorted(os.listdir(folder)) == ["0.mjb.zlib", "zarr.json"]
    import mujoco
    model = simloader.models.load_model("cartpole")
    assert os.path.getsize(os.path.join(folder, "0.mjb.zlib")) < mujoco.mj_sizeModel(model) / 3


def test_a_damaged_model_file_is_named(tmp_path):
    path = str(tmp_path / "w.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    name = os.path.join(path, "provenance", "models", "0.mjb.zlib")
    with open(name, "wb") as f:
        f.write(b"not a model")
    with pytest.raises(ValueError, match=r"the store's model .*0\.mjb\.zlib cannot be read"):
        from simloader.store import pixels
        pixels.load_models(simloader.StoredDataset(path), 1)


def test_a_store_root_with_an_impossible_models_entry_is_named(tmp_path):
    path = str(tmp_path / "v.zarr")
    simloader.write(tiny(), path, batches=1, progress=False)
    root = os.path.join(path, "zarr.json")
    meta = json.load(open(root))
    meta["attributes"]["simloader"]["models"] = {"kind": "variants", "count": 1}
    json.dump(meta, open(root, "w"))
    with pytest.raises(ValueError, match=r"says its models are .*'variants'.* edited or "
                                         r"damaged; pass model="):
        simloader.StoredDataset(path, cameras=simloader.Camera(-1, height=8, width=8))
