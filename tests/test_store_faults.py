"""A store at the sizes and under the faults users meet: thousands of slots read under a small
file limit, a second writer refused and a killed one's lock taken over, names that try to
leave the store, damaged shards named and repaired, edited metadata refused (CPU backend)."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import simloader
import simloader.cli
from simloader.store import zarr_format as store_format, lock, order
from simloader.store.shards import MAX_OPEN, DamagedStore

zarr = pytest.importorskip("zarr")

NSLOTS = 1500


def tiny(**kwargs):
    base = dict(backend="cpu", nbatch=2, nstep=3, nthread=1, seed=3, record=("state",),
                control=simloader.controls.Uniform())
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


@pytest.fixture(scope="module")
def big_store(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("big") / "big.zarr")
    simloader.write(tiny(), path, batches=NSLOTS, progress=False)
    return path


READ_ALL = """
import resource, sys, numpy as np, torch, simloader
resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))
stored = simloader.StoredDataset(sys.argv[1])
seen, total = 0, 0.0
loader = torch.utils.data.DataLoader(stored, batch_size=64, shuffle=True, num_workers=2)
for batch in loader:
    seen += len(batch["state"])
    total += float(batch["control"].sum())
transitions = stored.transitions()
counts = {}
for order in ("random", "quasi_random"):
    n, s = 0, 0.0
    for batch in transitions.loader(512, order=order, num_workers=2):
        n += len(batch["control"])
        s += float(batch["control"].sum())
    counts[order] = (n, s)
print(seen, repr(total), len(transitions), counts["random"][0], repr(counts["random"][1]),
      counts["quasi_random"][0], repr(counts["quasi_random"][1]))
"""


def test_a_store_of_1500_slots_is_read_whole_and_shuffled_under_ulimit_256(big_store):
    """Every trajectory and every transition of 1500 slots, shuffled, with two workers,
    under `ulimit -n 256` (the reader once held ~5 files per slot it had touched)."""
    out = subprocess.run([sys.executable, "-c", READ_ALL, big_store], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    seen, total, ntransitions, n1, s1, n2, s2 = out.stdout.split()
    control = zarr.open_group(big_store, mode="r")["control"][...]
    assert int(seen) == NSLOTS * 2
    assert np.isclose(float(total), control.sum())
    assert int(ntransitions) == int(n1) == int(n2) == control.shape[0] * control.shape[1]
    assert np.isclose(float(s1), control.sum()) and np.isclose(float(s2), control.sum())


def test_open_shards_stay_under_the_cap_and_transitions_end(big_store):
    from simloader.store import shards
    stored = simloader.StoredDataset(big_store)
    for i in np.random.default_rng(0).permutation(len(stored))[:600]:
        stored[int(i)]
    assert len(shards.OPEN_SHARDS) <= MAX_OPEN
    opened = len(os.listdir(f"/proc/{os.getpid()}/fd"))
    assert opened < MAX_OPEN + 40, f"{opened} file descriptors open"
    transitions = stored.transitions()
    assert len(transitions) == NSLOTS * 2 * 3
    with pytest.raises(IndexError):
        transitions[len(transitions)]
    assert torch.equal(transitions[-1]["control"], transitions[len(transitions) - 1]["control"])
    count = sum(1 for _ in iter(stored.transitions("state")))  # iteration ends
    assert count == len(transitions)
    # a quasi-random epoch reads ahead on threads that end with their files
    import threading
    seen = sum(len(b["control"]) for b in transitions.loader(4096))
    assert seen == len(transitions)
    deadline = time.monotonic() + 10
    while any(t.name == "simloader-read-ahead" for t in threading.enumerate()) and \
            time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [t for t in threading.enumerate() if t.name == "simloader-read-ahead"]


def test_quasi_random_order_reads_blocks_and_visits_every_index_once():
    n, block = 10_000, 100
    sampler = order.BlockOrder(n, 256, "quasi_random", block=block, window=4, seed=1)
    batches = list(sampler)
    flat = np.concatenate(batches)
    assert sorted(flat.tolist()) == list(range(n))
    # each window's batches come from at most `window` blocks (+1 where a batch straddles two)
    assert max(len(np.unique(np.asarray(b) // block)) for b in batches) <= 8
    assert all((np.diff(b) > 0).all() for b in batches)  # a set, read in file order
    quasi = order.mean_jump(sampler)
    random = order.mean_jump(order.BlockOrder(n, 256, "random", seed=1))
    sequential = order.mean_jump(order.BlockOrder(n, 256, "sequential"))
    assert sequential == 1.0 and 50 < quasi < random and random > n / 4
    again = order.BlockOrder(n, 256, "quasi_random", block=block, window=4, seed=1)
    first, second = next(iter(again)), next(iter(again))
    assert np.array_equal(first, batches[0]) and not np.array_equal(second, batches[0])  # per epoch
    with pytest.raises(ValueError, match="order: expected one of"):
        order.BlockOrder(n, 256, "shuffled")
    # each window is announced once (to be read ahead), one window before its first batch
    told, seen = [], []
    ahead = order.BlockOrder(n, 256, "quasi_random", block=block, window=4, seed=1,
                             ahead=lambda blocks, size: told.append(set(blocks.tolist())))
    for b in ahead:
        blocks = set((np.asarray(b) // block * block).tolist())
        seen.append(len(told))
        assert any(blocks <= t for t in told[:len(told)]) or len(blocks) > 1
    assert len(told) == n // block // 4 and set().union(*told) == set(range(0, n, block))
    assert seen[0] == 2  # the first window, and the next one ahead of it


def long_writer():
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=64, nstep=400, nthread=1,
                                seed=3, control=simloader.controls.Uniform(), prefetch=1)


def test_a_second_writer_is_refused_and_a_killed_writers_lock_is_taken_over(
        tmp_path, started_writer):
    path, batches = str(tmp_path / "l.zarr"), 30
    proc = started_writer(path, batches, slot=1, seed=3)  # the stream of long_writer()
    try:
        assert proc.poll() is None, "the first writer ended before it could be raced"
        holder = lock.holder(path)
        assert holder["pid"] == proc.pid
        with pytest.raises(lock.StoreLocked, match=rf"being written by process {proc.pid} on "
                                                   rf"host .*writing since"):
            simloader.write(long_writer(), path, batches=batches, progress=False)
        with pytest.raises(lock.StoreLocked):  # another configuration: refused the same way
            simloader.write(tiny(), path, batches=2, progress=False)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # a file a killed writer left half written (atomic_write's temporary name), and the
    # lock it never released
    stale = os.path.join(path, "state", "c", "0", "0", f"0.{'0a' * 16}.partial")
    open(stale, "wb").close()
    assert lock.holder(path)["pid"] == proc.pid
    simloader.write(long_writer(), path, batches=batches, progress=False)  # takes over
    assert not os.path.exists(stale)
    assert lock.holder(path) is None  # released
    clean = simloader.write(long_writer(), tmp_path / "clean.zarr", batches=batches,
                            progress=False)
    a, b = zarr.open_group(path, mode="r"), zarr.open_group(clean, mode="r")
    for key in ("state", "control", "initial_state"):
        assert np.array_equal(a[key][...], b[key][...])


class Extras(torch.nn.Module):
    def forward(self, obs):
        u = -obs["qpos"][:, :1]
        return u, {"../../../../escaped": u[:, 0], "a/b": u[:, 0] * 2}


ESCAPING = """
<mujoco>
  <worldbody>
    <body name="../../../../body">
      <joint name="slide" type="slide"/>
      <geom size=".1" mass="1"/>
      <site name="s"/>
    </body>
  </worldbody>
  <actuator><motor joint="slide"/></actuator>
  <sensor>
    <jointpos name="../../../../escaped" joint="slide"/>
    <framepos name="/abs/path" objtype="site" objname="s"/>
  </sensor>
</mujoco>
"""


def test_names_from_the_model_and_the_policy_cannot_leave_the_store(tmp_path):
    store = tmp_path / "inside" / "deep" / "n.zarr"
    dr = simloader.randomize
    ds = simloader.SimDataset(
        ESCAPING, backend="cpu", nbatch=2, nstep=3, nthread=1, policy=Extras(),
        record=("state", "qpos", "sensor:../../../../escaped", "sensor:/abs/path"),
        randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="../../../../body")])
    simloader.write(ds, store, batches=2, progress=False)
    outside = [os.path.join(d, f) for d, _, files in os.walk(tmp_path) for f in files
               if not os.path.abspath(d).startswith(os.path.abspath(store))]
    assert outside == []
    assert not os.path.exists("/abs")
    stored = simloader.StoredDataset(store)
    item = stored[3]
    assert {"sensor:../../../../escaped", "sensor:/abs/path", "policy/../../../../escaped",
            "policy/a/b"} <= set(item)
    assert any("../../../../body" in k for k in item["params"])
    assert torch.equal(item["policy/a/b"], 2 * item["policy/../../../../escaped"])
    group = zarr.open_group(str(store), mode="r")  # zarr reads the encoded names too
    assert np.array_equal(group["sensor:..%2F..%2F..%2F..%2Fescaped"][3],
                          item["sensor:../../../../escaped"].numpy())
    assert store_format.store_path("camera/../x/rgb") == "camera/%2E.%2Fx/rgb"
    assert store_format.store_path("..") == "%2E."
    assert store_format.store_path("__x") == "%5F_x"


def shard(path, key, slot):
    return os.path.join(path, key, "c", str(slot), "0", "0")


@pytest.mark.parametrize("damage", ["truncated", "emptied", "flipped", "removed"])
def test_a_damaged_shard_is_named_at_read_and_repaired_by_resuming(tmp_path, damage):
    path = simloader.write(tiny(), tmp_path / "d.zarr", batches=4, progress=False)
    clean = simloader.write(tiny(), tmp_path / "clean.zarr", batches=4, progress=False)
    file = shard(path, "state", 2)
    data = open(file, "rb").read()
    if damage == "removed":
        os.unlink(file)
    else:
        with open(file, "wb") as f:
            f.write({"truncated": data[:len(data) // 2], "emptied": b"",
                     "flipped": data[:5] + bytes([data[5] ^ 1]) + data[6:]}[damage])
    if damage == "flipped":  # same size: only the checksums see it
        simloader.StoredDataset(path)
        with pytest.raises(DamagedStore, match=r"slot\(s\) \[2\].*state/c/2/0/0: CRC-32"):
            simloader.StoredDataset(path, verify=True)
    else:
        with pytest.raises(DamagedStore, match=r"damaged batch slot\(s\) \[2\].*state/c/2/0/0"):
            simloader.StoredDataset(path)
    simloader.write(tiny(), path, batches=4, progress=False)  # resumes: repairs slot 2
    simloader.StoredDataset(path, verify=True)
    a, b = zarr.open_group(path, mode="r"), zarr.open_group(clean, mode="r")
    for key in ("state", "control", "initial_state", "diverged", "provenance/batch"):
        assert np.array_equal(a[key][...], b[key][...]), key


def edit(file, change):
    meta = json.load(open(file))
    change(meta)
    json.dump(meta, open(file, "w"))


def test_edited_metadata_is_refused_naming_the_file(tmp_path):
    path = simloader.write(tiny(), tmp_path / "m.zarr", batches=3, progress=False)
    state = os.path.join(path, "state", "zarr.json")
    root = os.path.join(path, "zarr.json")
    original = {f: open(f).read() for f in (state, root)}

    def restore():
        for f, text in original.items():
            open(f, "w").write(text)

    cases = [
        (state, lambda m: m.update(data_type="float32"),
         r"state/zarr.json: edited: data_type 'float32', written as 'float64'"),
        (state, lambda m: m.update(shape=[m["shape"][0], m["shape"][2], m["shape"][1]]),
         r"state/zarr.json: edited: trailing shape \[\d+, \d+\], written as"),
        (state, lambda m: m.update(data_type="complex64"),
         r"state/zarr.json: edited: data_type 'complex64'"),
        (root, lambda m: m["attributes"]["simloader"].update(nbatch=3),
         r"zarr.json: shards of 2 rows, the store's root says nbatch=3"),
        (root, lambda m: m["attributes"]["simloader"].update(batches=10**9),
         r"batches is 1000000000, but .*provenance/written/zarr.json has 3 slots"),
        (root, lambda m: m["attributes"]["simloader"].update(nbatch="2"),
         r"simloader.nbatch is .2., expected an int >= 1"),
    ]
    for file, change, message in cases:
        edit(file, change)
        start = time.perf_counter()
        with pytest.raises(DamagedStore, match=message):
            simloader.StoredDataset(path)
        assert time.perf_counter() - start < 1.0
        restore()
    # batches of 10^9 in the root and its slot array alike: opened without probing slots
    edit(root, lambda m: m["attributes"]["simloader"].update(batches=10**9))
    written = os.path.join(path, "provenance", "written", "zarr.json")
    edit(written, lambda m: m.update(shape=[10**9]))
    start = time.perf_counter()
    assert len(simloader.StoredDataset(path)) == 6
    assert time.perf_counter() - start < 1.0
    restore()
    open(os.path.join(path, "state", "zarr.json"), "w").write("{not json")
    with pytest.raises(DamagedStore, match=r"state/zarr.json: not valid JSON"):
        simloader.StoredDataset(path)
    restore()
    # a shard linked to another slot's (it would read slot 0's data as slot 1's)
    os.unlink(shard(path, "state", 1))
    os.symlink(shard(path, "state", 0), shard(path, "state", 1))
    with pytest.raises(DamagedStore, match=r"holds links.*state/c/1/0/0"):
        simloader.StoredDataset(path)


def test_the_cli_refuses_a_locked_store_with_a_message(tmp_path, capsys):
    path = str(tmp_path / "c.zarr")
    held = lock.WriterLock(path, "another-job").acquire()
    try:
        with pytest.raises(SystemExit, match=rf"simloader write: path: the store at .* is "
                                             rf"being written by process {os.getpid()}"):
            simloader.cli.main(["write", "cartpole", "--out", path, "--backend", "cpu",
                                "--nbatch", "2", "--nstep", "3", "--batches", "1"])
    finally:
        held.release()
    assert lock.holder(path) is None


def test_a_store_written_anew_at_the_same_path_is_read_anew(tmp_path):
    """Open shards are keyed by the array that opened them, not by path: a store replaced by
    one of other sizes at the same path, in the same process, is read from its own files."""
    import shutil
    path = str(tmp_path / "same.zarr")
    simloader.write(tiny(), path, batches=2, progress=False)
    first = simloader.StoredDataset(path)
    first[0], len(first.transitions())
    shutil.rmtree(path)
    simloader.write(tiny(nbatch=3, nstep=4, seed=9), path, batches=2, progress=False)
    again = simloader.StoredDataset(path)
    group = zarr.open_group(path, mode="r")
    assert np.array_equal(again[4]["state"].numpy(), group["state"][4])
    assert len(again.transitions()) == 6 * 4


CONTINUED_WINDOWS = """
import resource, sys, simloader
resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))
windows = simloader.StoredDataset(sys.argv[1]).windows(4)
n = sum(len(b["state"]) for b in windows.loader(64, num_workers=2))
print(len(windows), n)
"""


def test_windows_of_a_continued_store_of_600_slots_under_ulimit_256(tmp_path):
    """A continued stream runs across every slot of its worker: building its frame table
    read the provenance of all 600 slots (once as views that kept each map, and its
    descriptor, open: refused at slot 249), then every window, read by two workers."""
    path = simloader.write(tiny(continue_episodes=True), tmp_path / "c.zarr", batches=600,
                           progress=False)
    out = subprocess.run([sys.executable, "-c", CONTINUED_WINDOWS, path], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    count, read = map(int, out.stdout.split())
    assert count == read == 2 * (600 * 3 + 1 - 3)  # per row: 1 initial + 1800 frames
