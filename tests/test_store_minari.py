"""write_minari: real simulated batches written as a Minari dataset and read back by Minari."""

import json

import numpy as np
import pytest

minari = pytest.importorskip("minari")
pytest.importorskip("h5py")  # Minari's "hdf5" data format

import gymnasium  # noqa: E402  (minari depends on it)

import simloader  # noqa: E402
from simloader.store.minari import write_minari  # noqa: E402

NBATCH, NSTEP, NUM_BATCHES = 3, 5, 2


def _simulate():
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=NBATCH, nstep=NSTEP,
                              num_batches=NUM_BATCHES, control=simloader.controls.Uniform(),
                              nthread=1)
    return ds, [{k: v.numpy() for k, v in b.items()} for b in ds]


@pytest.fixture(scope="module")
def simulated():
    ds, batches = _simulate()
    # write_minari only reads the `diverged` flag; an edited control of 1e30 (cartpole clamps it
    # to its ctrlrange, so the physics does not actually blow up) stands for the runaway input
    # and checks that huge actions round-trip unchanged.
    b = batches[1]
    b["control"] = b["control"].copy()
    b["control"][1, 2:] = 1e30
    b["diverged"] = b["diverged"].copy()
    b["diverged"][1] = True
    return ds, batches


def test_write_and_load(simulated, tmp_path, monkeypatch):
    ds, batches = simulated
    meta = {"description": ds.describe(), "fingerprint": "abc123",
            "versions": {"simloader": simloader.__version__}}
    seen = []
    out = write_minari(iter(batches), tmp_path, dataset_id="simloader/cartpole-v0",
                       total_episodes=NBATCH * NUM_BATCHES, metadata=meta, progress=seen.append)
    assert out == str(tmp_path / "simloader" / "cartpole-v0")
    assert seen == [3, 6]

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("simloader/cartpole-v0")
    assert dataset.total_episodes == 6 and dataset.total_steps == 6 * NSTEP
    nobs, nact = batches[0]["state"].shape[2], batches[0]["control"].shape[2]
    assert dataset.observation_space == gymnasium.spaces.Box(-np.inf, np.inf, (nobs,), np.float64)
    assert dataset.action_space == gymnasium.spaces.Box(-np.inf, np.inf, (nact,), np.float64)

    episodes = list(dataset.iterate_episodes())
    for k, ep in enumerate(episodes):
        b, i = batches[k // NBATCH], k % NBATCH
        want_obs = np.concatenate([b["initial_state"][i][None], b["state"][i]])
        np.testing.assert_array_equal(ep.observations, want_obs)
        np.testing.assert_array_equal(ep.actions, b["control"][i])
        np.testing.assert_array_equal(ep.rewards, np.zeros(NSTEP))
        diverged = bool(b["diverged"][i])
        assert diverged == (k == NBATCH + 1)
        want_term = np.zeros(NSTEP, bool)
        want_trunc = np.zeros(NSTEP, bool)
        (want_term if diverged else want_trunc)[-1] = True
        np.testing.assert_array_equal(ep.terminations, want_term)
        np.testing.assert_array_equal(ep.truncations, want_trunc)
    assert episodes[NBATCH + 1].actions[2:].min() == 1e30

    stored = dataset.storage.metadata
    # the caller's metadata, with the write's progress record (complete: Minari opens it)
    assert stored["simloader"] == {**meta, "complete": True, "episodes_written": 6,
                                   "total_episodes": 6, "minari_version": minari.__version__}
    assert stored["minari_version"] == minari.__version__
    assert stored["description"] == meta["description"]
    json.dumps(stored["simloader"])


def test_stops_at_total_episodes_and_refuses_reuse(simulated, tmp_path):
    _, batches = simulated

    def endless():
        while True:
            yield from batches

    out = write_minari(endless(), tmp_path, dataset_id="cut-v0", total_episodes=4)
    assert minari.MinariDataset(f"{out}/data").total_episodes == 4
    with pytest.raises(ValueError, match="dataset_id.*already exists"):
        write_minari(batches, tmp_path, dataset_id="cut-v0", total_episodes=4)


def test_bad_batches(simulated, tmp_path):
    _, batches = simulated
    with pytest.raises(ValueError, match=r"batches\[0\].*missing \['control'\]"):
        write_minari([{k: v for k, v in batches[0].items() if k != "control"}], tmp_path,
                     dataset_id="bad-v0", total_episodes=3)
    # A bad second batch: the error names it, and no half-written dataset is left behind.
    wrong = dict(batches[1], initial_state=batches[1]["initial_state"][:, :2])
    with pytest.raises(ValueError, match=r"batches\[1\]\['initial_state'\]: expected shape"):
        write_minari([batches[0], wrong], tmp_path, dataset_id="bad-v0", total_episodes=6)
    # (only the dataset's lock file stays: a lock file is never removed)
    assert os.listdir(tmp_path / "bad-v0") == ["simloader.lock"]
    assert store_minari.status(tmp_path / "bad-v0")["simloader"] is False
    with pytest.raises(ValueError, match="total_episodes.*ended after 3"):
        write_minari(batches[:1], tmp_path, dataset_id="bad-v0", total_episodes=6)
    with pytest.raises(ValueError, match="metadata.*JSON"):
        write_minari(batches, tmp_path, dataset_id="bad-v0", total_episodes=6,
                     metadata={"x": object()})


def test_simloader_write_format_minari(tmp_path, monkeypatch):
    """`simloader.write(..., format="minari")`: the dataset named by the path's last part,
    a genuinely diverged trajectory terminated, the store's provenance in the metadata."""
    control = np.zeros((NBATCH, NSTEP, 1))
    control[2, 1] = np.inf  # trajectory 2 of every batch diverges
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=NBATCH, nstep=NSTEP,
                              control=control, nthread=1)
    out = simloader.write(ds, tmp_path / "cartpole-still-v0", batches=2, format="minari",
                          progress=False)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("cartpole-still-v0")
    assert dataset.total_episodes == 2 * NBATCH and str(out).endswith("cartpole-still-v0")
    episodes = list(dataset.iterate_episodes())
    assert [bool(e.terminations[-1]) for e in episodes] == [False, False, True] * 2
    assert [bool(e.truncations[-1]) for e in episodes] == [True, True, False] * 2
    meta = dataset.storage.metadata["simloader"]
    assert meta["fingerprint"]["nstep"] == NSTEP and meta["versions"]["mujoco"]
    first = next(ds.batches_at([0]))[1]
    np.testing.assert_array_equal(episodes[1].observations[1:], first["state"][1].numpy())
    with pytest.raises(ValueError, match="format: 'minari' stores the recorded 'state'"):
        simloader.write(simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3,
                                             record=("qpos",)),
                        tmp_path / "qpos-v0", batches=1, format="minari", progress=False)


# --- an interrupted write: marked incomplete, refused by Minari, resumed by simloader.write ---

import os  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from simloader.store import minari as store_minari  # noqa: E402
from simloader.store.provenance import provenance  # noqa: E402

KILL_NBATCH, KILL_NSTEP, KILL_BATCHES = 2, 20, 60

# A writer of the dataset below, killed by the test mid-way.
KILLED_MINARI_WRITER = """
import sys
import simloader
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=int(sys.argv[2]),
                          nstep=int(sys.argv[3]), control=simloader.controls.Uniform(),
                          nthread=1, seed=7)
simloader.write(ds, sys.argv[1], batches=int(sys.argv[4]), format="minari", progress=False)
"""


def _killable(nstep=KILL_NSTEP):
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=KILL_NBATCH, nstep=nstep,
                                control=simloader.controls.Uniform(), nthread=1, seed=7)


def _episodes_of(dataset_dir):
    dataset = minari.MinariDataset(os.path.join(dataset_dir, "data"))
    return [(e.observations, e.actions, e.terminations, e.truncations)
            for e in dataset.iterate_episodes()]


def _kill_mid_way(path, nstep=KILL_NSTEP):
    """Starts a writer of KILL_BATCHES batches and SIGKILLs it once 3 are recorded."""
    proc = subprocess.Popen([sys.executable, "-c", KILLED_MINARI_WRITER, str(path),
                             str(KILL_NBATCH), str(nstep), str(KILL_BATCHES)])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        written = store_minari.status(path)["episodes_written"]
        if written is not None and written >= 3 * KILL_NBATCH:
            break
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    found = store_minari.status(path)
    assert found["simloader"] and found["complete"] is False, found
    assert 3 * KILL_NBATCH <= found["episodes_written"] < KILL_BATCHES * KILL_NBATCH, \
        "the writer was not killed mid-way"
    return found


def test_a_killed_writer_is_marked_incomplete_and_resumes_to_a_clean_write(tmp_path,
                                                                             monkeypatch):
    path = tmp_path / "killed-v0"
    found = _kill_mid_way(path)
    assert found["total_episodes"] == KILL_BATCHES * KILL_NBATCH
    assert found["episodes_in_file"] >= found["episodes_written"]
    # Minari itself refuses to open it, and says why.
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(ValueError, match=r"simloader-incomplete: \d+ of 120 episodes written"):
        minari.load_dataset("killed-v0")
    with pytest.raises(ValueError, match="simloader-incomplete"):
        minari.MinariDataset(path / "data")

    out = simloader.write(_killable(), path, batches=KILL_BATCHES, format="minari",
                          progress=False)  # resumes
    assert store_minari.status(out) == {
        "path": str(path), "exists": True, "simloader": True, "complete": True,
        "episodes_written": 120, "total_episodes": 120, "episodes_in_file": 120,
        "minari_total_episodes": 120}
    clean = simloader.write(_killable(), tmp_path / "clean-v0", batches=KILL_BATCHES,
                            format="minari", progress=False)
    resumed, want = _episodes_of(out), _episodes_of(clean)
    assert len(resumed) == len(want) == KILL_BATCHES * KILL_NBATCH
    for got, ref in zip(resumed, want):
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
    loaded = minari.load_dataset("killed-v0")
    assert loaded.total_steps == 120 * KILL_NSTEP
    assert loaded.storage.metadata["minari_version"] == minari.__version__
    assert loaded.storage.metadata["simloader"] == \
        minari.load_dataset("clean-v0").storage.metadata["simloader"]
    assert not (path / ".simloader-metadata.json").exists()


def _extra_episode_and_truncated_metadata(path, written):
    """What a kill can leave besides: the batch in flight committed but not recorded, a
    batch file half written, and metadata.json cut short."""
    import shutil
    episodes = path / ".simloader-episodes"
    last = sorted(episodes.glob("*.hdf5"))[-1]
    shutil.copy(last, episodes / f"{written:012d}-{written + KILL_NBATCH:012d}.hdf5")
    (episodes / f"{written + KILL_NBATCH:012d}-{written + 2 * KILL_NBATCH:012d}.hdf5."
                f"{'0' * 32}.partial").write_bytes(b"\x89HDF torn")
    (path / "data" / "metadata.json").write_text('{"total_episodes": ')


def test_resume_drops_unrecorded_episodes_and_restores_truncated_metadata(tmp_path):
    ds = _killable()
    path = tmp_path / "cut-v0"
    clean = simloader.write(ds, tmp_path / "whole-v0", batches=4, format="minari",
                            progress=False)

    def interrupt(n):
        if n >= 2 * KILL_NBATCH:
            raise KeyboardInterrupt  # simloader.write keeps the dataset, resumable

    with pytest.raises(KeyboardInterrupt):
        store_minari._write(
            ({k: v.numpy() for k, v in b.items()} for _, b in ds.batches_at(range(4))),
            "cut-v0", str(path), total_episodes=4 * KILL_NBATCH,
            observation_key="state", metadata=provenance(ds, 4), progress=interrupt, done=0,
            first_index=0, create=True, keep_partial=True)
    _extra_episode_and_truncated_metadata(path, 2 * KILL_NBATCH)
    found = store_minari.status(path)
    assert (found["complete"], found["episodes_written"], found["episodes_in_file"]) == \
        (False, 2 * KILL_NBATCH, 3 * KILL_NBATCH)
    simloader.write(ds, path, batches=4, format="minari", progress=False)
    for got, ref in zip(_episodes_of(path), _episodes_of(clean), strict=True):
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
    assert store_minari.status(path)["complete"] is True


def test_a_complete_dataset_is_refused_unless_replace(tmp_path):
    path = tmp_path / "done-v0"
    simloader.write(_killable(), path, batches=1, format="minari", progress=False)
    with pytest.raises(ValueError, match=r"path: '.*done-v0' already holds a complete simloader "
                                         r"Minari dataset \(2 episodes\); pass replace=True"):
        simloader.write(_killable(), path, batches=2, format="minari", progress=False)
    simloader.write(_killable(nstep=3), path, batches=2, format="minari", progress=False,
                    replace=True)
    episodes = _episodes_of(path)
    assert len(episodes) == 4 and episodes[0][1].shape == (3, 1)
    assert store_minari.status(path)["complete"] is True


def test_an_incomplete_dataset_of_another_configuration_is_refused_unless_replace(tmp_path):
    path = tmp_path / "other-v0"
    found = _kill_mid_way(path)
    with pytest.raises(ValueError, match=r"holds an incomplete simloader Minari dataset \(\d+ of "
                                         r"120 episodes written\) of another configuration "
                                         r"\(nstep: stored 20, given 3\).*replace=True"):
        simloader.write(_killable(nstep=3), path, batches=2, format="minari", progress=False)
    assert store_minari.status(path)["episodes_written"] == found["episodes_written"]
    ds = _killable(nstep=3)
    store_minari.write(ds, str(path), batches=2, num_workers=0, progress=False, replace=True)
    assert store_minari.status(path)["complete"] is True
    assert [e[1].shape for e in _episodes_of(path)] == [(3, 1)] * 4


def test_a_foreign_minari_dataset_is_refused(tmp_path, simulated):
    _, batches = simulated
    out = write_minari(batches, tmp_path, dataset_id="plain-v0", total_episodes=3)
    raw = json.loads(open(f"{out}/data/metadata.json").read())
    raw.pop("simloader", None)  # as another tool (or an older simloader) leaves it
    open(f"{out}/data/metadata.json", "w").write(json.dumps(raw))
    assert store_minari.status(out)["complete"] is None
    with pytest.raises(ValueError, match="without simloader's progress record.*replace=True"):
        simloader.write(_killable(), out, batches=1, format="minari", progress=False)


# --- what is never removed, the lock, a full disk, killed creations, per-episode values ---

import errno  # noqa: E402
import re  # noqa: E402

from simloader.store.lock import StoreLocked, WriterLock  # noqa: E402


def _tiny(nbatch=2, nstep=5, **kwargs):
    kwargs.setdefault("control", simloader.controls.Uniform())
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=nbatch, nstep=nstep,
                                nthread=1, seed=3, **kwargs)


def _tree(folder):
    return sorted((str(p.relative_to(folder)), p.read_bytes() if p.is_file() else None)
                  for p in folder.rglob("*"))


def test_replace_refuses_a_folder_that_is_not_a_minari_dataset(tmp_path):
    project = tmp_path / "project-v0"
    (project / "src").mkdir(parents=True)
    (project / "src" / "train.py").write_text("print('train')\n")
    (project / "notes.txt").write_text("notes\n")
    before = _tree(project)
    for replace in (True, False):
        with pytest.raises(ValueError, match=r"path: '.*project-v0': expected a Minari dataset "
                                             r".* found a folder holding \['notes.txt', "
                                             r"'src/'\], which is not a Minari dataset; "
                                             r"nothing was written or removed"):
            simloader.write(_tiny(), project, batches=1, format="minari", progress=False,
                            replace=replace)
    assert _tree(project) == before  # not even a lock file was put there
    a_file = tmp_path / "file-v0"
    a_file.write_text("x")
    with pytest.raises(ValueError, match="found a file"):
        simloader.write(_tiny(), a_file, batches=1, format="minari", progress=False,
                        replace=True)
    assert a_file.read_text() == "x"


def test_a_dataset_id_without_a_version_is_refused_before_anything_is_removed(tmp_path,
                                                                                simulated):
    _, batches = simulated
    out = write_minari(batches, tmp_path, dataset_id="mine-v0", total_episodes=3)
    unversioned = tmp_path / "mine"
    os.rename(out, unversioned)  # a Minari dataset's folder, named without -vN
    before = _tree(unversioned)
    with pytest.raises(ValueError, match=r"path: expected the last component of '.*mine' to "
                                         r"be a Minari dataset id ending in a version '-v<N>'"):
        simloader.write(_tiny(), unversioned, batches=1, format="minari", progress=False,
                        replace=True)
    assert _tree(unversioned) == before
    with pytest.raises(ValueError, match=r"dataset_id: expected dataset_id to be a Minari "
                                         r"dataset id ending in a version"):
        write_minari(batches, tmp_path, dataset_id="simloader/nover", total_episodes=3)
    assert not (tmp_path / "simloader").exists()


def test_a_second_writer_is_refused_even_with_replace_and_the_dataset_kept(tmp_path):
    path = tmp_path / "held-v0"
    simloader.write(_tiny(), path, batches=1, format="minari", progress=False)
    episodes = _episodes_of(path)
    other = WriterLock(str(path), "job-other").acquire()  # another writer holds it
    try:
        for replace in (False, True):
            with pytest.raises(StoreLocked, match=rf"being written by process {os.getpid()}"):
                simloader.write(_tiny(nstep=3), path, batches=2, format="minari",
                                progress=False, replace=replace)
    finally:
        other.release()
    fresh = WriterLock(str(tmp_path / "fresh-v0"), "job-other").acquire()
    try:
        with pytest.raises(StoreLocked, match="being written by"):
            write_minari([], tmp_path, dataset_id="fresh-v0", total_episodes=1)
    finally:
        fresh.release()
    for got, ref in zip(_episodes_of(path), episodes, strict=True):
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
    # released: the next writer takes it
    simloader.write(_tiny(nstep=3), path, batches=2, format="minari", progress=False,
                    replace=True)
    assert [e[1].shape for e in _episodes_of(path)] == [(3, 1)] * 4


def test_a_lock_file_that_is_a_link_is_refused_and_not_followed(tmp_path):
    path = tmp_path / "linked-v0"
    simloader.write(_tiny(), path, batches=1, format="minari", progress=False)
    outside = tmp_path / "precious.txt"
    outside.write_text("keep me")
    os.unlink(path / "simloader.lock")
    os.symlink(outside, path / "simloader.lock")
    with pytest.raises(ValueError, match=r"symbolic link\(s\) \['simloader.lock'\]"):
        simloader.write(_tiny(), path, batches=1, format="minari", progress=False,
                        replace=True)
    assert outside.read_text() == "keep me"
    assert store_minari.status(path)["complete"] is True


class _DiskFills:
    """h5py.File whose `at`-th open for writing hits a full disk: the file is cut where the
    disk ran out (its end never written) and OSError(ENOSPC) is raised, as HDF5 leaves a file
    appended to on a full disk."""

    def __init__(self, at):
        import h5py
        self.at, self.opens, self.real = at, 0, h5py.File
        fills = self

        class File(h5py.File):
            def __init__(self, name, mode="r", *args, **kwargs):
                super().__init__(name, mode, *args, **kwargs)
                self._fill_at = None
                if mode != "r":
                    fills.opens += 1
                    if fills.opens == fills.at:
                        self._fill_at = os.fspath(name)

            def __exit__(self, *exc):
                super().__exit__(*exc)
                if self._fill_at is not None:
                    size = os.path.getsize(self._fill_at)
                    os.truncate(self._fill_at, size // 2)
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), self._fill_at)

        self.File = File


@pytest.mark.parametrize("at", [3, 6], ids=["third-batch", "assembling"])
def test_a_full_disk_leaves_a_resumable_dataset(tmp_path, monkeypatch, at):
    import h5py
    path = tmp_path / "full-v0"
    fills = _DiskFills(at)
    monkeypatch.setattr(h5py, "File", fills.File)
    with pytest.raises(OSError) as raised:
        simloader.write(_killable(nstep=5), path, batches=4, format="minari", progress=False)
    assert raised.value.errno == errno.ENOSPC
    monkeypatch.setattr(h5py, "File", fills.real)
    found = store_minari.status(path)
    assert found["complete"] is False and found["episodes_written"] >= KILL_NBATCH
    simloader.write(_killable(nstep=5), path, batches=4, format="minari", progress=False)
    # the error said what is left and what to do; the full disk's remains were removed
    assert re.search(r"No space left on device while writing the Minari dataset .* "
                     r"resumable .* calling write again", str(raised.value))
    assert not (path / ".simloader-merging").exists()
    assert not list(path.rglob("*.partial"))
    clean = simloader.write(_killable(nstep=5), tmp_path / "room-v0", batches=4,
                            format="minari", progress=False)
    for got, ref in zip(_episodes_of(path), _episodes_of(clean), strict=True):
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
    assert store_minari.status(path)["complete"] is True
    assert sorted(os.listdir(path)) == ["data", "simloader.lock"]


def test_a_killed_creations_folder_of_this_dataset_is_removed_and_nothing_else(tmp_path):
    def staging(where, *inside):
        where.mkdir(parents=True)
        for name in inside:
            (where / name / "data").mkdir(parents=True)
            (where / name / "data" / "metadata.json").write_text("{}")
        return where

    # as earlier versions left them, in the datasets root; and in the dataset's folder
    ours = staging(tmp_path / ".simloader-creating-ab12cd_9", "left-v0")
    inside = staging(tmp_path / "left-v0" / ".simloader-creating-zz99yy88", "left-v0")
    keep = [staging(tmp_path / ".simloader-creating-qq11ww22", "other-v0"),  # other dataset
            staging(tmp_path / ".simloader-creating-ee33rr44", "left-v0", "other-v0"),
            staging(tmp_path / ".simloader-creating-short", "left-v0"),  # not mkdtemp's
            staging(tmp_path / ".simloader-creating-tt55yy66x", "left-v0"),
            staging(tmp_path / "my-folder", "left-v0")]
    outside = tmp_path / "outside"
    staging(outside, "left-v0")
    os.symlink(outside, tmp_path / ".simloader-creating-uu77ii88")  # a link: not followed
    simloader.write(_tiny(), tmp_path / "left-v0", batches=1, format="minari", progress=False)
    assert not ours.exists() and not inside.exists()
    assert all(k.exists() for k in keep) and (outside / "left-v0" / "data").exists()
    assert store_minari.status(tmp_path / "left-v0")["complete"] is True


def test_episodes_hold_their_randomized_values_and_actions_their_control_limits(tmp_path,
                                                                                 monkeypatch):
    from simloader import randomize as dr
    ds = _tiny(nbatch=3, randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0))])
    out = simloader.write(ds, tmp_path / "masses-v0", batches=2, format="minari",
                          progress=False)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("masses-v0")
    assert dataset.action_space == gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float64)
    want = [b["params"]["body_mass"][i].numpy()
            for _, b in ds.batches_at(range(2)) for i in range(3)]
    episodes = list(dataset.iterate_episodes())
    assert len(episodes) == 6
    for ep, mass in zip(episodes, want):
        rows = ep.infos["params"]["body_mass"]
        assert rows.shape == (5 + 1, mass.shape[0])
        np.testing.assert_array_equal(rows, np.broadcast_to(mass, rows.shape))
    assert len({tuple(m) for m in want}) == 6  # each episode its own
    assert str(out).endswith("masses-v0")

    # other control_spec components (qfrc_applied: one column per dof) are unbounded
    uniform = simloader.controls.Uniform
    ds = _tiny(control_spec="ctrl|qfrc_applied",
               control={"ctrl": uniform(), "qfrc_applied": uniform()})
    simloader.write(ds, tmp_path / "forces-v0", batches=1, format="minari", progress=False)
    space = minari.load_dataset("forces-v0").action_space
    np.testing.assert_array_equal(space.low, [-1.0, -np.inf, -np.inf])
    np.testing.assert_array_equal(space.high, [1.0, np.inf, np.inf])
    assert minari.load_dataset("forces-v0")[0].infos == {}
