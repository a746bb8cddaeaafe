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
    ds = simloader.SimDataset("cartpole", backend="rollout", nbatch=NBATCH, nstep=NSTEP,
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
    assert stored["simloader"] == meta
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
    ds = simloader.SimDataset("cartpole", backend="rollout", nbatch=NBATCH, nstep=NSTEP,
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
        simloader.write(simloader.SimDataset("cartpole", backend="rollout", nbatch=2, nstep=3,
                                             record=("qpos",)),
                        tmp_path / "qpos-v0", batches=1, format="minari", progress=False)
