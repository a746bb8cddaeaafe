"""simloader.write and StoredDataset: zarr v3 stores of simulated batches, read back by zarr
itself and by StoredDataset, resumed after a kill, written by workers and ranks, and
regenerated bit for bit from their provenance (CPU backend)."""

import errno
import glob
import json
import os
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

import simloader
from simloader.batch import flat
from simloader.store.folder import StoreFolder
from simloader.store import pipeline, zarr_format as store_format, provenance

zarr = pytest.importorskip("zarr")
dr = simloader.randomize


class Gain(torch.nn.Module):
    """A policy with an extra: control = -gain * qpos[0], extras {"effort": |control|}."""

    def __init__(self):
        super().__init__()
        self.gain = torch.nn.Parameter(torch.ones(1, dtype=torch.float64))

    def forward(self, obs):
        u = -self.gain * obs["qpos"][:, :1]
        return u, {"effort": u.abs()[:, 0], "flags": (u > 0)[:, 0]}


def rich(**kwargs):
    """Every key kind: mjSTATE rows, sensors, an int field, camera rgb/depth/segmentation
    (images big enough to be compressed), randomization params."""
    base = dict(backend="cpu", nbatch=3, nstep=6, nthread=1, seed=5, record_every=2,
                control=simloader.controls.Uniform(),
                randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole")],
                record=("state", "sensordata", "qpos", "ncon",
                        simloader.Camera(-1, height=24, width=32, depth=True,
                                         segmentation=True)))
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


def plain(**kwargs):
    """rich() without the camera (rendering dominates the time of the tests that use it)."""
    return rich(**{"record": ("state", "sensordata", "qpos", "ncon"), "record_every": 1,
                   **kwargs})


def reference(ds, batches):
    """The stream's first `batches` batches, as one writer simulates them, concatenated."""
    got = [flat(b) for _, b in ds.batches_at(range(batches))]
    return {k: torch.cat([g[k].reshape(-1, *g[k].shape[1:]) if g[k].ndim else
                          g[k].expand(ds.config.nbatch) for g in got]) for k in got[0]}


def test_round_trip_every_key_kind_through_zarr_and_stored_dataset(tmp_path):
    ds = rich()
    path = simloader.write(ds, tmp_path / "s.zarr", batches=2, progress=False)
    want = reference(rich(), 2)
    group = zarr.open_group(path, mode="r")
    for key, value in want.items():
        array = group[key]
        assert array.shape == tuple(value.shape) and array.dtype == value.numpy().dtype, key
        assert np.array_equal(array[...], value.numpy()), key  # zarr reads it as written
    # images are compressed, float arrays raw
    codecs = json.load(open(os.path.join(path, "camera/free/rgb/zarr.json")))["codecs"]
    assert [c["name"] for c in codecs[0]["configuration"]["codecs"]] == ["bytes", "zstd"]
    stored = simloader.StoredDataset(path)
    assert len(stored) == 6
    for i in range(6):
        item = flat(stored[i])
        assert set(item) == set(want)
        for key, value in item.items():
            assert value.dtype == want[key].dtype and torch.equal(value, want[key][i]), key
    assert stored.provenance(4) == {"rank": 0, "batch": 1, "row": 1, "num_workers": 1}
    only = simloader.StoredDataset(path, keys=["qpos", "params"])
    assert set(flat(only[0])) == {"qpos", "params/body_mass[pole]"}
    with pytest.raises(KeyError, match="did you mean 'qpos'"):
        simloader.StoredDataset(path, keys=["qpso"])


def test_policy_extras_and_version_are_kept_per_trajectory(tmp_path):
    policy = Gain()
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=5, nthread=1,
                              policy=policy, record=("qpos",))
    path = simloader.write(ds, tmp_path / "p.zarr", batches=2, progress=False)
    group = zarr.open_group(path, mode="r")
    assert group["policy/effort"].shape == (4, 5) and group["policy/flags"].dtype == bool
    assert group["policy/version"][...].tolist() == [group["policy/version"][0]] * 4
    item = simloader.StoredDataset(path)[3]
    assert torch.equal(item["policy/effort"], item["control"][:, 0].abs())
    with pytest.raises(ValueError, match="policy= stream cannot be regenerated"):
        simloader.StoredDataset(path).regenerate(ds, 0)


def test_regenerates_stored_trajectories_bit_for_bit(tmp_path):
    path = simloader.write(rich(), tmp_path / "r.zarr", batches=3, progress=False)
    stored = simloader.StoredDataset(path)
    again = rich(num_batches=None)  # its own num_batches does not matter
    for i in (0, 7):
        item, regenerated = flat(stored[i]), flat(stored.regenerate(again, i))
        assert all(torch.equal(item[k], regenerated[k]) for k in item)
    with pytest.raises(ValueError, match="seed: stored 5, given 6"):
        stored.regenerate(rich(seed=6), 0)


def test_continued_episodes_regenerate_from_their_workers_stream(tmp_path):
    """Continued episodes depend on the worker's earlier batches: regeneration replays them."""
    make = lambda: simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=4,
                                        nthread=1, continue_episodes=True,
                                        control=simloader.controls.Uniform())
    path = simloader.write(make(), tmp_path / "c.zarr", batches=4, num_workers=2,
                           progress=False)
    stored = simloader.StoredDataset(path)
    assert [stored.provenance(i)["num_workers"] for i in (0, 7)] == [2, 2]
    for i in (1, 6, 7):  # batches 0 and 3: worker 0's first and worker 1's second
        item, regenerated = stored[i], stored.regenerate(make(), i)
        assert all(torch.equal(item[k], regenerated[k]) for k in item)
    # consecutive batches of one worker continue each other
    assert torch.equal(stored[4]["initial_state"], stored[0]["state"][-1])


def test_workers_write_disjoint_slots_of_one_store(tmp_path):
    one = simloader.write(plain(), tmp_path / "one.zarr", batches=4, progress=False)
    two = simloader.write(plain(), tmp_path / "two.zarr", batches=4, num_workers=2,
                          progress=False)
    a, b = simloader.StoredDataset(one), simloader.StoredDataset(two)
    assert len(a) == len(b) == 12
    for i in range(12):
        x, y = flat(a[i]), flat(b[i])
        assert all(torch.equal(x[k], y[k]) for k in x)
    assert sorted({b.provenance(i)["num_workers"] for i in range(12)}) == [2]


def cartpole():
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=64, nstep=400, nthread=1,
                                control=simloader.controls.Uniform(), prefetch=1)


def test_a_killed_writer_leaves_a_readable_store_that_resumes(tmp_path, started_writer):
    path, batches = str(tmp_path / "k.zarr"), 40
    proc = started_writer(path, batches, slot=2)  # the stream of cartpole()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    stored = simloader.StoredDataset(path)
    done = len(stored) // 64
    assert 3 <= done < batches, "the writer was not killed mid-way"
    want = reference(cartpole(), batches)
    assert torch.equal(stored[len(stored) - 1]["state"], want["state"][len(stored) - 1])
    simloader.write(cartpole(), path, batches=batches, progress=False)  # resumes
    stored = simloader.StoredDataset(path)
    assert len(stored) == batches * 64
    group = zarr.open_group(path, mode="r")
    assert np.array_equal(group["state"][...], want["state"].numpy())
    assert not [f for _, _, files in os.walk(path) for f in files if f.endswith(".partial")]


def test_appending_grows_the_store_and_another_configuration_is_refused(tmp_path):
    path = simloader.write(plain(), tmp_path / "a.zarr", batches=1, progress=False)
    simloader.write(plain(), path, batches=3, progress=False)
    assert len(simloader.StoredDataset(path)) == 9
    assert zarr.open_group(path, mode="r")["state"].shape == (9, 6, 5)
    with pytest.raises(ValueError, match=r"nstep: stored 6, given 7"):
        simloader.write(plain(nstep=7), path, batches=3, progress=False)
    with pytest.raises(ValueError, match=r"record:"):
        simloader.write(plain(record=("qpos",)), path, batches=3, progress=False)


def test_another_simulator_version_is_refused(tmp_path, monkeypatch):
    path = simloader.write(plain(), tmp_path / "v.zarr", batches=1, progress=False)
    real = provenance.versions()
    monkeypatch.setattr(provenance, "versions", lambda: {**real, "mujoco": "0.0.1"})
    with pytest.raises(ValueError, match=r"mujoco .* \(now 0.0.1\)"):
        simloader.write(plain(), path, batches=2, progress=False)


@pytest.mark.parametrize("kwargs, match", [
    ({"batches": 0}, "batches: expected a positive int, got 0"),
    ({"batches": 1, "format": "hdf5"}, "format: expected 'zarr' or 'minari', got 'hdf5'"),
    ({"batches": 1, "num_workers": -1}, "num_workers: expected an int >= 0, got -1"),
])
def test_bad_arguments_name_themselves(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        simloader.write(plain(), tmp_path / "b.zarr", progress=False, **kwargs)


def test_a_full_disk_leaves_a_readable_store_and_says_so(tmp_path, monkeypatch):
    """The disk fills up in the middle of the third batch: the first two stay readable, the
    error says so, and writing again (space freed) completes the store."""
    path = str(tmp_path / "f.zarr")
    real, calls = StoreFolder.stage, []

    def fills_up(folder, name, parts):
        if "/c/2/" in name:
            calls.append(name)
            if len(calls) == 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), folder.where(name))
        return real(folder, name, parts)

    monkeypatch.setattr(StoreFolder, "stage", fills_up)
    with pytest.raises(OSError, match="No space left on device .* stays readable with the "
                                      "batches completed so far"):
        simloader.write(plain(), path, batches=4, progress=False)
    # slots 0 and 1, and slot 3 if its commit (pipelined with slot 2's) finished first
    assert len(simloader.StoredDataset(path)) in (6, 9)
    assert not glob.glob(os.path.join(path, "**", "*.partial"), recursive=True)
    monkeypatch.setattr(StoreFolder, "stage", real)
    simloader.write(plain(), path, batches=4, progress=False)
    want = reference(plain(), 4)
    stored = simloader.StoredDataset(path)
    assert all(torch.equal(flat(stored[i])["state"], want["state"][i]) for i in range(12))


def test_stored_dataset_feeds_a_shuffling_loader_with_workers(tmp_path):
    path = simloader.write(rich(), tmp_path / "l.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path, keys=["state", "camera"])
    loader = torch.utils.data.DataLoader(stored, batch_size=4, shuffle=True, num_workers=2,
                                         multiprocessing_context="fork")
    seen = [b["state"] for b in loader]
    assert sum(len(s) for s in seen) == 6 and seen[0].shape[1:] == (3, 5)
    rows = sorted(tuple(r.flatten().tolist()) for s in seen for r in s)
    assert rows == sorted(tuple(stored[i]["state"].flatten().tolist()) for i in range(6))


def test_transitions_pair_each_state_with_its_control_and_successor(tmp_path):
    path = simloader.write(plain(), tmp_path / "t.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path)
    transitions = stored.transitions()
    assert len(transitions) == 6 * 6
    first, later = transitions[6], transitions[6 + 3]  # trajectory 1, frames 0 and 3
    item = stored[1]
    assert torch.equal(first["state"], item["initial_state"])
    assert torch.equal(first["next/state"], item["state"][0])
    assert torch.equal(later["state"], item["state"][2])
    assert torch.equal(later["control"], item["control"][3])
    # other keys start at frame 1 (no stored initial value)
    qpos = stored.transitions("qpos")
    assert len(qpos) == 6 * 5 and torch.equal(qpos[0]["qpos"], stored[0]["qpos"][0])
    batch = next(iter(torch.utils.data.DataLoader(transitions, batch_size=8, shuffle=True)))
    assert batch["state"].shape == (8, 5) and batch["control"].shape == (8, 1)
    every = simloader.write(plain(record=("state",), record_every=2), tmp_path / "e.zarr",
                            batches=1, progress=False)
    pairs = simloader.StoredDataset(every).transitions()
    assert len(pairs) == 9 and pairs[1]["control"].shape == (2, 1)


TWO_RANKS = """
import os, sys, torch, simloader
torch.distributed.init_process_group("gloo")
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=5, nthread=1,
                          control=simloader.controls.Uniform())
simloader.write(ds, sys.argv[1], batches=5, progress=False)
torch.distributed.destroy_process_group()
"""


def test_two_ranks_write_one_store_under_torchrun(tmp_path):
    script = tmp_path / "two_ranks.py"
    script.write_text(TWO_RANKS)
    path = str(tmp_path / "d.zarr")
    subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2",
                    str(script), path], check=True, timeout=300, cwd=tmp_path,
                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    stored = simloader.StoredDataset(path)
    assert len(stored) == 10
    where = [stored.provenance(i) for i in range(0, 10, 2)]
    # slot s = batch * world + rank: ranks alternate, each rank's batches in order
    assert [(w["rank"], w["batch"]) for w in where] == [(0, 0), (1, 0), (0, 1), (1, 1), (0, 2)]
    make = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=5, nthread=1,
                                control=simloader.controls.Uniform())
    for i in (2, 3, 9):  # rank 1's trajectories are its own stream, rank 0's too
        assert all(torch.equal(stored[i][k], stored.regenerate(make, i)[k]) for k in stored[i])
    # slot i * ranks + rank: resuming with another number of ranks would store some batches
    # twice and others never, so it is refused, saying with how many to resume
    with pytest.raises(ValueError, match=r"written by 2 rank\(s\) .* with 2, not 1"):
        simloader.write(make, path, batches=5, progress=False)


def test_a_key_without_values_round_trips(tmp_path):
    """A model without sensors records `sensordata` of width 0: kept, with no shard files."""
    xml = """<mujoco><worldbody><body><freejoint/><geom size="0.1"/></body></worldbody>
             </mujoco>"""
    ds = simloader.SimDataset(xml, backend="cpu", nbatch=2, nstep=3, nthread=1)
    path = simloader.write(ds, tmp_path / "z.zarr", batches=1, progress=False)
    assert zarr.open_group(path, mode="r")["sensordata"].shape == (2, 3, 0)
    item = simloader.StoredDataset(path)[1]
    assert item["sensordata"].shape == (3, 0) and item["state"].shape[0] == 3


def test_cli_writes_a_store_and_refuses_another_configuration(tmp_path, capsys):
    from simloader import cli
    out = str(tmp_path / "cli.zarr")
    common = ["write", "cartpole", "--out", out, "--backend", "cpu", "--nbatch", "4",
              "--batches", "2", "--record", "qpos,qvel"]
    cli.main(common + ["--nstep", "5"])
    said = capsys.readouterr().out
    assert "wrote 2 x 4 trajectories of 5 steps" in said
    # the closing line: each stage's time and what bounded the run
    assert re.search(r"write: 2 batches, 40 steps .* seconds per batch: simulate [0-9.e-]+, "
                     r"copy to host .*sync [0-9.e-]+; .* bound by the (simulator|disk|CPU|copy)",
                     said), said
    stored = simloader.StoredDataset(out)
    assert len(stored) == 8 and set(stored[0]) >= {"qpos", "qvel", "control"}
    with pytest.raises(SystemExit) as exit:
        cli.main(common + ["--nstep", "6"])
    assert exit.value.code == 2
    assert "nstep: stored 5, given 6" in capsys.readouterr().err


def test_transitions_leave_out_diverged_trajectories_unless_kept(tmp_path):
    control = np.zeros((3, 6, 1))
    control[1, 2] = np.inf  # trajectory 1 of every batch diverges
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=3, nstep=6, nthread=1,
                              control=control)
    path = simloader.write(ds, tmp_path / "d.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path)
    assert stored.flagged().tolist() == [False, True, False] * 2
    dropped = stored.transitions()
    assert len(dropped) == 4 * 6 and len(stored.transitions(diverged="keep")) == 6 * 6
    assert torch.equal(dropped[6]["state"], stored[2]["initial_state"])  # 2nd kept: row 2
    every = torch.cat([b["next/state"] for b in dropped.loader(5, shuffle=False)])
    assert torch.isfinite(every).all() and len(every) == 24
    with pytest.raises(ValueError, match="diverged: expected 'drop' or 'keep', got 'no'"):
        stored.transitions(diverged="no")


def test_images_without_numcodecs_are_refused_before_anything_runs(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "numcodecs", None)  # as if the extra were not installed
    ds = rich(num_batches=1)
    with pytest.raises(ImportError, match=r"need numcodecs: pip install 'simloader\[zarr\]'"):
        simloader.write(ds, tmp_path / "store", batches=1, progress=False)
    assert not (tmp_path / "store").exists() and ds.stats["batches"] == 0


def test_a_full_disk_in_a_worker_says_so_without_the_workers_traceback(tmp_path, monkeypatch):
    """The error a DataLoader worker raises reaches `write` as the worker's whole traceback:
    the message keeps its last line (errno, reason, file), the traceback stays the cause."""
    path = str(tmp_path / "w.zarr")
    real = StoreFolder.stage

    def full(folder, name, parts):
        if "/c/1/" in name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), folder.where(name))
        return real(folder, name, parts)

    monkeypatch.setattr(StoreFolder, "stage", full)  # inherited by the forked worker
    with pytest.raises(OSError) as raised:
        simloader.write(plain(), path, batches=3, num_workers=1, progress=False)
    said = str(raised.value)
    assert raised.value.errno == errno.ENOSPC and "/c/1/" in raised.value.filename
    assert said.startswith("[Errno 28] write: No space left on device while writing the store")
    assert "Traceback" not in said and "stays readable" in said


def test_a_store_root_without_its_fingerprint_is_refused_by_name(tmp_path):
    path = simloader.write(plain(), tmp_path / "r.zarr", batches=1, progress=False)
    root = os.path.join(path, "zarr.json")
    meta = json.load(open(root))
    del meta["attributes"]["simloader"]["fingerprint"]
    json.dump(meta, open(root, "w"))
    with pytest.raises(ValueError, match=r"lacks \['fingerprint'\] in its root's 'simloader' "
                                         r"attribute .*zarr.json was edited or damaged"):
        simloader.write(plain(), path, batches=2, progress=False)


def test_describe_says_what_the_store_keeps_on_disk(tmp_path):
    path = simloader.write(plain(), tmp_path / "d.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs)
    steps = len(stored) * stored.info["nstep"]
    line = stored.describe().splitlines()[0]
    assert line == (f"kept: {len(stored)} trajectories of {stored.info['nstep']} steps in 2 "
                    f"committed batch slots, {size / 1e6:,.1f} MB on disk, "
                    f"{size / steps:,.0f} bytes per step"), line
