"""The write pipeline (`simloader.store.pipeline`): a slot's commit mark follows its data on
the disk, a writer killed at random moments resumes to the same store bit for bit, the
per-stage report, and `compression="zstd"` (CPU engine)."""

import json
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

import simloader
from simloader.store.folder import StoreFolder
from simloader.store import integrity, pipeline, zarr_format as store_format

zarr = pytest.importorskip("zarr")


def cartpole(**kwargs):
    base = dict(backend="cpu", nbatch=8, nstep=40, nthread=1, seed=5,
                control=simloader.controls.Uniform(), record=("state", "sensordata"))
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


def arrays(path):
    """Every array of a store, by path, as NumPy (through zarr-python)."""
    out = {}
    group = zarr.open_group(path, mode="r")
    for name, array in group.arrays():
        out[name] = array[...]
    for name, sub in group.groups():
        out.update({f"{name}/{k}": v for k, v in arrays(os.path.join(path, name)).items()})
    return out


def _named(name, dir_fd):
    """The path of `name`, relative to folder descriptor `dir_fd` where one is given (the
    store's writer renames relative to the folder it holds open)."""
    if dir_fd is None:
        return os.path.abspath(name)
    return os.path.join(os.readlink(f"/proc/self/fd/{dir_fd}"), name)


class Operations:
    """Every fsync and rename of the process, in order, with the file each one touched
    (threads included: the pipeline's commits run in its threads)."""

    def __init__(self, monkeypatch):
        self.log, self.lock = [], threading.Lock()
        real_fsync, real_replace = os.fsync, os.replace

        def fsync(fd):
            where = os.readlink(f"/proc/self/fd/{fd}")
            real_fsync(fd)  # logged once done: what is logged is on the disk
            with self.lock:
                self.log.append(("fsync", where))

        def replace(src, dst, *, src_dir_fd=None, dst_dir_fd=None):
            real_replace(src, dst, src_dir_fd=src_dir_fd, dst_dir_fd=dst_dir_fd)
            with self.lock:
                self.log.append(("rename", _named(src, src_dir_fd), _named(dst, dst_dir_fd)))

        monkeypatch.setattr(os, "fsync", fsync)
        monkeypatch.setattr(os, "replace", replace)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name fds")
def test_a_slots_mark_follows_its_data_files_and_their_names_on_the_disk(tmp_path,
                                                                          monkeypatch):
    """For every slot: each shard file was fsync'd under its temporary name, then renamed,
    then every directory that names it fsync'd, and its checksums made durable the same way,
    all before the slot's mark was renamed into place; and the mark's own directory is
    fsync'd after it (a power loss at any moment leaves no mark without its data)."""
    ops = Operations(monkeypatch)
    path = os.path.abspath(str(tmp_path / "o.zarr"))
    batches = 6
    simloader.write(cartpole(), path, batches=batches, progress=False)
    log = ops.log
    for slot in range(batches):
        mark = os.path.join(path, store_format.WRITTEN.shard_key(slot))
        marks = [i for i, op in enumerate(log) if op[0] == "rename" and op[2] == mark]
        assert len(marks) == 1, f"slot {slot}: its mark was renamed {len(marks)} times"
        at = marks[0]
        files = [(i, op) for i, op in enumerate(log) if op[0] == "rename"
                 and re.search(rf"/c/{slot}(/|$)", op[2][len(path):]) and op[2] != mark]
        names = {op[2][len(path) + 1:].split("/c/")[0] for _, op in files}
        assert "state" in names and "provenance/checksum" in names, names
        for i, (_, temporary, final) in files:
            assert i < at, f"slot {slot}: {final} was renamed after the slot's mark"
            synced = [j for j, op in enumerate(log[:i]) if op == ("fsync", temporary)]
            assert synced, f"slot {slot}: {final} was renamed before its data was fsync'd"
            directory = os.path.dirname(final)
            while len(directory) > len(path):
                named = [j for j, op in enumerate(log) if op == ("fsync", directory)
                         and i < j < at]
                assert named, (f"slot {slot}: the directory {directory} naming {final} was "
                               f"not fsync'd between the file's rename and the slot's mark")
                if directory.endswith("/c"):
                    break
                directory = os.path.dirname(directory)
        # the checksums are durable before the mark, the mark durable after
        checksum = next(i for i, op in files if "provenance/checksum" in op[2])
        assert checksum > max(i for i, op in files if "provenance/checksum" not in op[2])
        after = [j for j, op in enumerate(log) if op == ("fsync", os.path.dirname(mark))
                 and j > at]
        assert after, f"slot {slot}: the mark's directory was not fsync'd after the mark"


_KILLED = """
import sys, simloader
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=32, nstep=300, nthread=1, seed=11,
                          control=simloader.controls.Uniform(), prefetch=1,
                          record=("state", "sensordata"))
simloader.write(ds, sys.argv[1], batches=int(sys.argv[2]), progress=False,
                compression=sys.argv[3] if sys.argv[3] != "none" else None)
"""


# ten kills of each in the slow runs; the suite (its time) kills a compressed store's writer
# four times: the same pipeline, with the slower commits that widen the window a kill lands in
@pytest.mark.parametrize("compression, times", [
    pytest.param(None, 10, marks=pytest.mark.slow),
    pytest.param("zstd", 10, marks=pytest.mark.slow), ("zstd", 4)])
def test_a_writer_killed_at_random_moments_resumes_to_the_same_store(tmp_path, compression,
                                                                      times):
    """kill -9 while slots are in the pipeline (copied, written, synced, renamed), `times`
    times: after each kill every committed slot is intact, and the store completed by the
    resumed writers equals an uninterrupted write bit for bit."""
    path, batches = str(tmp_path / "k.zarr"), 48
    rng = random.Random(7)
    script = [sys.executable, "-c", _KILLED, path, str(batches), str(compression).lower()]
    kills, committed = 0, []
    while kills < times:
        proc = subprocess.Popen(script)
        # a random moment once it writes (the import and the store's check take a while)
        marks = os.path.join(path, store_format.WRITTEN.name, "c")
        before = len(os.listdir(marks)) if os.path.isdir(marks) else 0
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline and (
                not os.path.isdir(marks) or len(os.listdir(marks)) <= before):
            time.sleep(0.005)
        time.sleep(rng.uniform(0.0, 0.15))
        if proc.poll() is not None:
            break  # it finished first: the last kills found nothing left to write
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        kills += 1
        store = integrity.Store(StoreFolder(path))
        assert not store.damaged(list(store.slots), verify=True), \
            f"kill {kills}: a committed slot lacks its data or its checksum differs"
        committed.append(len(store.slots))
    assert kills >= min(times, 5) and committed[-1] < batches, \
        f"the writer was killed {kills} times (committed: {committed}): too fast to kill"
    simloader.write(simloader.SimDataset(
        "cartpole", backend="cpu", nbatch=32, nstep=300, nthread=1, seed=11,
        control=simloader.controls.Uniform(), prefetch=1, record=("state", "sensordata")),
        path, batches=batches, progress=False, compression=compression)
    clean = str(tmp_path / "clean.zarr")
    subprocess.run(script[:3] + [clean] + script[4:], check=True)
    got, want = arrays(path), arrays(clean)
    assert sorted(got) == sorted(want)
    for name in want:
        if name == "provenance/num_workers":
            continue
        assert np.array_equal(got[name], want[name]), name
    assert not [f for _, _, fs in os.walk(path) for f in fs if f.endswith(".partial")]


def test_the_report_names_each_stage_and_the_bound(tmp_path):
    path = simloader.write(cartpole(), tmp_path / "r.zarr", batches=4, progress=False)
    report = path.report
    assert isinstance(path, str) and os.path.isdir(path)
    assert report.batches == 4 and report.steps == 4 * 8 * 40 and report.writers == 1
    assert set(pipeline.STAGES) - {"copy to host", "compress"} <= set(report.stages)
    assert report.stages["write"] > 0 and report.stages["sync"] > 0
    said = str(report)
    for stage in pipeline.STAGES:
        assert stage in said
    assert "bound by" in said and report.bound in said
    # resumed with nothing left to write: nothing to report, no division by zero
    again = simloader.write(cartpole(), path, batches=4, progress=False)
    assert again.report.batches == 0 and "bound by" in str(again.report)


def test_the_bound_is_the_stage_that_waited_least():
    report = pipeline.WriteReport(batches=10, steps=100, seconds=10.0, writers=1, threads=4,
                                  stages={"simulate": 6.0, pipeline._WAITED: 0.5,
                                          "write": 3.0, "sync": 2.0})
    assert report.bound == "the simulator"
    report.stages = {"simulate": 0.1, pipeline._WAITED: 5.0, "write": 3.0, "sync": 6.0,
                     "checksum": 8.0, "copy to host": 1.0}
    assert report.bound == "the disk (write + sync)"
    report.stages["compress"] = 30.0  # 38 s over 4 threads of 10 s: busier than the disk
    assert report.bound == "the CPU (compress + checksum)"


def test_compression_zstd_stores_the_same_values_in_fewer_bytes(tmp_path):
    ds = cartpole(nstep=200, record=("state", "qvel"))  # 200 x 4 floats: 6.4 KB chunks
    raw = simloader.write(ds, tmp_path / "raw.zarr", batches=2, progress=False)
    packed = simloader.write(ds, tmp_path / "z.zarr", batches=2, progress=False,
                             compression="zstd")
    meta = json.load(open(os.path.join(packed, "state", "zarr.json")))
    inner = meta["codecs"][0]["configuration"]["codecs"]
    assert [c["name"] for c in inner] == ["bytes", "blosc"]
    assert inner[1]["configuration"]["shuffle"] == "shuffle"
    a, b = arrays(raw), arrays(packed)
    assert sorted(a) == sorted(b) and "state" in a
    for name in a:  # zarr-python decodes it too; only the files' checksums differ
        assert name == "provenance/checksum" or np.array_equal(a[name], b[name]), name
    stored = simloader.StoredDataset(packed)
    assert torch.equal(stored[3]["state"], simloader.StoredDataset(raw)[3]["state"])

    def size(p):
        return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(p)
                   for f in fs if "/state/" in os.path.join(d, f))
    assert size(packed) < 0.95 * size(raw)
    # resuming it with another compression is refused, naming the codecs
    with pytest.raises(ValueError, match=r"'state'.*codecs"):
        simloader.write(ds, packed, batches=3, progress=False)


@pytest.mark.parametrize("value", ["gzip", True, "ZSTD"])
def test_an_unknown_compression_is_refused(tmp_path, value):
    with pytest.raises(ValueError, match=r"compression: expected one of \[None, 'zstd'\], got"):
        simloader.write(cartpole(), tmp_path / "c.zarr", batches=1, compression=value)
    assert not os.path.exists(tmp_path / "c.zarr")
