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
    assert not (tmp_path / "bad-v0").exists()
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
    first = next(iter(ds.stream(ds.make_backend(), [0])))[1]
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
    """What a kill can leave besides: the batch in flight appended to the HDF5 file but not
    recorded, and Minari's in-place metadata.json cut short."""
    import h5py
    with h5py.File(path / "data" / "main_data.hdf5", "a") as f:
        f.create_group(f"episode_{written}").create_dataset("observations", data=[1.0])
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
            ({k: v.numpy() for k, v in b.items()} for _, b, _ in
             ds.stream(ds.make_backend(), range(4))),
            "cut-v0", str(path), total_episodes=4 * KILL_NBATCH,
            observation_key="state", metadata=provenance(ds, 4), progress=interrupt, done=0,
            first_index=0, create=True, keep_partial=True)
    _extra_episode_and_truncated_metadata(path, 2 * KILL_NBATCH)
    found = store_minari.status(path)
    assert (found["complete"], found["episodes_written"], found["episodes_in_file"]) == \
        (False, 2 * KILL_NBATCH, 2 * KILL_NBATCH + 1)
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
    store_minari.write(ds, str(path), batches=2, metadata=provenance(ds, 2), progress=False,
                       replace=True)
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
