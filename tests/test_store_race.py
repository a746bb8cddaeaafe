"""A store's writer never writes outside the store, even when a folder of the store is swapped
for a link while it writes (Linux, CPU backend).

An attacker who may rename entries inside a store (a shared folder, a store another user can
write to) exchanges one of its folders with a symlink to a folder outside it, atomically
(`renameat2(RENAME_EXCHANGE)`), and back, again and again, while `write` runs: a link that
appears after the writer's checks. A writer that opens `ROOT/state/c/3/0/0` by its path follows
the link whenever the exchange is in place at that instant, and writes, renames or creates
files in the attacker's folder (an audit saw 9 writes of 32 do so, one of them rewriting
another folder's `zarr.json`, three of them reporting success). A writer that opens every file
relative to the store root's directory descriptor, component by component with O_NOFOLLOW,
refuses the link instead: it may raise, but nothing outside the store changes.

The swapper is a separate process (true concurrency, the GIL aside) that toggles one pair at a
time: a folder of the store (`state`, `state/c`, `provenance/written/c`, ...) and a symlink
to that pair's victim folder. The links wait in a holding folder beside the store, not inside
it: `write` refuses a store that holds a link at its checks (`integrity.survey`), so a link
parked inside the store would have every write refused before it writes anything, the old
writer's too, and the test would prove nothing. While a pair is exchanged the store's real
folder sits in the holding folder; exchanged back, it is in the store again. Only one pair is
exchanged at any moment (a nested folder is never exchanged through a swapped parent), and the
swapper leaves every pair in place when it stops.

Every attempt writes with the swapper running, at one of four paces (flat out to calm): a new
store, a store resumed or extended, or one replaced (`replace=True`), now and then through a
DataLoader worker. A write may succeed or raise any Exception (a refused link is a refusal;
a hang fails the test); after each one, every victim must hold exactly its files, byte for
byte, and nothing more. `pytest -s` shows the figures (attempts, exchanges, successes,
refusals, outside changes).
"""

import ctypes
import errno
import gc
import hashlib
import json
import os
import platform
import random
import select
import shutil
import subprocess
import sys
import threading
import time
import traceback

import pytest

import simloader

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="renameat2(RENAME_EXCHANGE) is Linux's")

AT_FDCWD = -100
RENAME_EXCHANGE = 2
SYSCALL = {"x86_64": 316, "amd64": 316, "aarch64": 276, "arm64": 276}  # renameat2's number

# The folders a writer descends into, swapped one at a time (each with a victim of its own):
# arrays, their chunk folders, the provenance group and the slots' marks and checksums.
TARGETS = ("state", "state/c", "control", "control/c", "sensordata/c", "provenance",
           "provenance/written", "provenance/written/c", "provenance/checksum",
           "provenance/checksum/c")

# What a victim holds: a zarr.json and files where a writer following a link to it would
# write one (`c/SLOT/0/0` below an array, `SLOT/0/0` below a chunk folder, `written/c/SLOT`
# below the provenance group, ...), so that a followed link overwrites something, not only
# adds files.
VICTIM = {
    "zarr.json": b'{"zarr_format": 3, "node_type": "array", "note": "not the store\'s"}\n',
    "notes.txt": b"the victim's own notes\n",
    "c/0/0/0": b"victim shard 0",
    "c/1/0/0": b"victim shard 1",
    "c/0/0.partial": b"victim partial",
    "0/0/0": b"victim chunk 0",
    "1/0/0": b"victim chunk 1",
    "c/2": b"victim mark 2",
    "written/zarr.json": b'{"victim": "written"}\n',
    "written/c/0": b"victim mark 0",
    "checksum/c/0/0/0": b"victim checksum",
    "deep/keep/me.bin": bytes(range(256)),
}

ATTEMPTS = 150  # at most; fewer when BUDGET_S runs out (a loaded CI machine)
BUDGET_S = 15.0  # seconds of attempts (150 took about 15 s on an idle 2-core machine)
# The swapper's paces: (seconds in place between two rounds, how long a link stays: spins or
# seconds). Flat out, a link is in place about half of the time and nearly every write is
# refused or fails; paced, writes get through between the rounds, and some succeed.
PACES = {
    "flat": (0.0, [0, 0, 1, 5, 30]),
    "fast": (0.0005, [0, 1, 5, 30, 0.0002, 0.001]),
    "paced": (0.003, [0, 5, 30, 0.0005, 0.002]),
    "calm": (0.02, [0, 30, 0.0002, 0.001]),
}
# Every 12th write simulates and writes in a DataLoader worker (forked).
WORKERS_EVERY = 12
WRITE_TIMEOUT_S = 120  # a write that takes longer hangs: the test fails, naming where

# The swapper: reads one command a line on stdin. "go PAIRS_JSON": toggles the pairs (one at a
# time: exchanged, then exchanged back, then the next, picked at random) until "stop", then
# prints its counts as JSON once every pair is back in place. EOF ends it.
SWAPPER = r"""
import ctypes, errno, json, os, platform, random, select, sys, time

libc = ctypes.CDLL(None, use_errno=True)
try:
    _renameat2 = libc.renameat2
    _renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                           ctypes.c_uint]
    def exchange(a, b):
        return 0 if _renameat2(-100, a, -100, b, 2) == 0 else ctypes.get_errno()
except AttributeError:  # glibc < 2.28
    _nr = {"x86_64": 316, "amd64": 316, "aarch64": 276, "arm64": 276}[platform.machine()]
    def exchange(a, b):
        return 0 if libc.syscall(_nr, -100, a, -100, b, 2) == 0 else ctypes.get_errno()

stdin = sys.stdin.buffer
rng = random.Random(int(sys.argv[1]))
while True:
    line = stdin.readline()
    if not line:
        break
    order = json.loads(line.split(b" ", 1)[1])
    pairs = [(a.encode(), b.encode()) for a, b in order["pairs"]]
    pause = order["pause"]  # seconds in place between two rounds (0: none)
    holds = order["holds"]  # how long a link stays: an int spins, a float sleeps (seconds)
    print("going", flush=True)
    exchanges = rounds = failed = 0
    broken = []  # pairs that could not be exchanged back (their folder went meanwhile)
    live = list(range(len(pairs)))
    stop = False
    while not stop:
        for _ in range(64 if not pause else 1):
            if not live:
                break
            i = rng.choice(live)
            store, holding = pairs[i]
            if exchange(store, holding):
                failed += 1  # not there yet (a new store) or gone (replace=True)
                continue
            exchanges += 1
            hold = rng.choice(holds)
            if isinstance(hold, int):
                for _ in range(hold):
                    pass
            else:
                time.sleep(hold)
            if exchange(store, holding):
                broken.append(i)
                live.remove(i)
            else:
                exchanges += 1
                rounds += 1
        ready, _, _ = select.select([stdin], [], [], pause * rng.random() * 2)
        if ready:
            stop = True
    if stdin.readline() == b"":
        break
    print(json.dumps({"exchanges": exchanges, "rounds": rounds, "failed": failed,
                      "broken": sorted(set(broken))}), flush=True)
"""


def _exchange_function():
    """renameat2(AT_FDCWD, a, AT_FDCWD, b, RENAME_EXCHANGE) through libc (the syscall where
    glibc is older than 2.28); returns errno (0: exchanged)."""
    libc = ctypes.CDLL(None, use_errno=True)
    try:
        call = libc.renameat2
        call.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                         ctypes.c_uint]
    except AttributeError:
        number = SYSCALL.get(platform.machine())
        if number is None:
            return None

        def call(fd_a, a, fd_b, b, flags):
            return libc.syscall(number, fd_a, a, fd_b, b, flags)

    def exchange(a, b):
        return 0 if call(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b),
                         RENAME_EXCHANGE) == 0 else ctypes.get_errno()
    return exchange


def require_exchange(folder):
    """Skips the test where the kernel, libc or file system cannot exchange a folder with a
    link atomically."""
    exchange = _exchange_function()
    if exchange is None:
        pytest.skip(f"renameat2: no libc symbol and no known syscall number on "
                    f"{platform.machine()}")
    probe = folder / "probe"
    os.makedirs(probe / "real")
    os.symlink(probe / "target", probe / "link")
    got = exchange(probe / "real", probe / "link")
    if got in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, errno.EPERM):
        pytest.skip(f"renameat2(RENAME_EXCHANGE) is refused here: {os.strerror(got)}")
    assert got == 0, os.strerror(got)
    assert os.path.islink(probe / "real") and os.path.isdir(probe / "link")
    shutil.rmtree(probe)


def make_victim(folder):
    for name, data in VICTIM.items():
        os.makedirs(os.path.dirname(os.path.join(folder, name)), exist_ok=True)
        with open(os.path.join(folder, name), "wb") as f:
            f.write(data)


def snapshot(folder):
    """Every entry below `folder` (never following a link): a file's SHA-256, a folder, a
    link's target."""
    out = {}
    for directory, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = os.path.join(directory, name)
            rel = os.path.relpath(path, folder)
            if os.path.islink(path):
                out[rel] = "link -> " + os.readlink(path)
            elif os.path.isdir(path):
                out[rel] = "folder"
            else:
                with open(path, "rb") as f:
                    out[rel] = hashlib.sha256(f.read()).hexdigest()
    return out


def differences(before, after):
    new = sorted(set(after) - set(before))
    gone = sorted(set(before) - set(after))
    changed = sorted(k for k in set(before) & set(after) if before[k] != after[k])
    return [f"new {n}" for n in new] + [f"changed {c}" for c in changed] + \
        [f"removed {g}" for g in gone]


class Swapper:
    """The swapper process: `start(pairs)` before a write, `stop()` after it (every pair back
    in place; returns the counts)."""

    def __init__(self, seed):
        self.proc = subprocess.Popen([sys.executable, "-c", SWAPPER, str(seed)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)

    def _line(self, timeout=30):
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        assert ready, "the swapper did not answer"
        line = self.proc.stdout.readline()
        assert line, f"the swapper ended (exit status {self.proc.poll()})"
        return line

    def start(self, pairs, pause, holds):
        order = {"pairs": [[str(a), str(b)] for a, b in pairs], "pause": pause,
                 "holds": holds}
        self.proc.stdin.write(b"go " + json.dumps(order).encode() + b"\n")
        self.proc.stdin.flush()
        assert self._line() == b"going\n"

    def stop(self):
        self.proc.stdin.write(b"stop\n")
        self.proc.stdin.flush()
        return json.loads(self._line())

    def close(self):
        """Ends the swapper: EOF on its stdin, or killed (a DataLoader worker forked from this
        process may still hold the pipe open)."""
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc.stdout.close()


def write_within(seconds, ds, store, **kwargs):
    """`simloader.write(ds, store, **kwargs)` on a thread of its own: None if it succeeded,
    the Exception it raised, or a failure naming where every thread stood if it still runs
    after `seconds` (a hang fails the test instead of the CI job; the thread is left)."""
    outcome = {}

    def run():
        try:
            simloader.write(ds, store, progress=False, **kwargs)
            outcome["error"] = None
        except BaseException as e:
            outcome["error"] = e

    thread = threading.Thread(target=run, name="race-write", daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        stacks = "\n".join(f"thread {ident}:\n{''.join(traceback.format_stack(frame))}"
                           for ident, frame in sys._current_frames().items())
        pytest.fail(f"simloader.write({str(store)!r}, {kwargs}) still runs after {seconds} s "
                    f"while a folder of the store is swapped for a link:\n{stacks}")
    error = outcome["error"]
    if error is not None and not isinstance(error, Exception):
        raise error  # KeyboardInterrupt, SystemExit: not a refusal
    return error


def committed(store):
    """How many slots a store marks written (its `provenance/written/c/SLOT` files)."""
    folder = os.path.join(store, "provenance", "written", "c")
    if os.path.islink(folder) or not os.path.isdir(folder):
        return 0
    return sum(1 for e in os.scandir(folder) if e.name.isdigit() and not e.is_symlink())


def dataset():
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=8, nthread=1,
                                seed=7, num_batches=None, control=simloader.controls.Uniform())


def test_a_folder_swapped_for_a_link_while_writing_never_leads_the_writer_outside(tmp_path,
                                                                                monkeypatch):
    require_exchange(tmp_path)
    # A DataLoader whose worker failed waits for it to notice the shutdown, up to torch's
    # status interval (5 s) per failed write; 0.5 s here (the worker reads it when forked)
    import torch.utils.data._utils as loader_utils
    import torch.utils.data._utils.worker as loader_worker
    monkeypatch.setattr(loader_utils, "MP_STATUS_CHECK_INTERVAL", 0.5, raising=False)
    monkeypatch.setattr(loader_worker, "MP_STATUS_CHECK_INTERVAL", 0.5, raising=False)
    victims, holding, stores = tmp_path / "victims", tmp_path / "holding", tmp_path / "stores"
    os.makedirs(stores)
    names = {t: t.replace("/", "__") for t in TARGETS}  # each pair's victim and link
    for t in TARGETS:
        make_victim(victims / names[t])
    clean = snapshot(victims / names[TARGETS[0]])  # every victim holds the same

    def park_links():
        """Each pair's link in the holding folder (a store's folder left there removed)."""
        os.makedirs(holding, exist_ok=True)
        for t in TARGETS:
            link, target = holding / names[t], str(victims / names[t])
            if os.path.islink(link) and os.readlink(link) == target:
                continue
            if os.path.isdir(link) and not os.path.islink(link):
                shutil.rmtree(link)
            elif os.path.lexists(link):
                os.unlink(link)
            os.symlink(target, link)

    park_links()
    ds = dataset()
    rng = random.Random(20240611)
    swapper = Swapper(seed=11)
    counts = dict(attempts=0, exchanges=0, rounds=0, succeeded=0, raised=0, slots=0,
                  outside=0, succeeded_outside=0, unreadable=0)
    kinds: dict[str, int] = {}
    paces: dict[str, list] = {p: [0, 0, 0] for p in PACES}  # attempts, successes, outside
    errors: dict[str, int] = {}
    through: dict[str, int] = {}  # the targets through which a victim changed
    changes = []  # (attempt, kind, pace, succeeded, [(target, differences)])
    unreadable = []
    store, last, batches = None, None, 0  # the store written to, the last one made
    started = time.monotonic()
    try:
        while counts["attempts"] < ATTEMPTS and time.monotonic() - started < BUDGET_S:
            attempt = counts["attempts"]
            counts["attempts"] += 1
            # a new store, or the last one resumed, extended or replaced
            kind = "new" if store is None else rng.choice(
                ["new", "new", "extend", "extend", "resume", "replace"])
            if kind == "new":
                if last is not None:
                    shutil.rmtree(last, ignore_errors=True)  # the disk holds one store at most
                store, batches = stores / f"s{attempt}.zarr", rng.randint(4, 8)
                last = store
            elif kind == "extend":
                batches += rng.randint(1, 4)
            elif kind == "replace":
                batches = rng.randint(4, 8)
            kinds[kind] = kinds.get(kind, 0) + 1
            workers = 1 if attempt % WORKERS_EVERY == WORKERS_EVERY - 1 else 0
            pace = rng.choice(list(PACES))
            paces[pace][0] += 1
            marks = committed(store)
            pairs = [(store / t, holding / names[t]) for t in TARGETS]
            swapper.start(pairs, *PACES[pace])
            try:
                error = write_within(WRITE_TIMEOUT_S, ds, store, batches=batches,
                                     num_workers=workers, replace=kind == "replace")
            finally:
                done = swapper.stop()
            ok = error is None
            if not ok:  # a refusal is fine: the victims are what is checked
                errors[type(error).__name__] = errors.get(type(error).__name__, 0) + 1
                del error
                if workers:
                    gc.collect()  # a failed DataLoader's workers are shut down now
            counts["exchanges"] += done["exchanges"]
            counts["rounds"] += done["rounds"]
            counts["succeeded" if ok else "raised"] += 1
            paces[pace][1] += ok
            counts["slots"] += max(0, committed(store) - marks)

            # the store and the holding folder as they were: no link left in the store (the
            # swapper puts every pair back; a pair whose folder a replace=True removed
            # meanwhile could not be), every link back in the holding folder
            links = [p for p, _ in pairs if os.path.islink(p)]
            for p in links:
                os.unlink(p)
            moved = [h for _, h in pairs if not os.path.islink(h)]
            park_links()
            if links or moved or done["broken"]:
                store = None  # a folder of it was left in the holding folder: not resumed

            # nothing outside the store changed: every victim as it was (then restored)
            outside = []
            for t in TARGETS:
                found = differences(clean, snapshot(victims / names[t]))
                if found:
                    outside.append((t, found))
                    through[t] = through.get(t, 0) + 1
                    shutil.rmtree(victims / names[t])
                    make_victim(victims / names[t])
            if outside:
                counts["outside"] += 1
                counts["succeeded_outside"] += ok
                paces[pace][2] += 1
                changes.append((attempt, kind, pace, ok, outside))
            if ok and store is not None:
                try:  # a write that said it succeeded: its store reads back whole (every
                    # slot its root names, at least the `batches` asked for)
                    with open(store / "zarr.json") as f:
                        slots = json.load(f)["attributes"]["simloader"]["batches"]
                    n = len(simloader.StoredDataset(store))
                    assert slots >= batches and n == slots * ds.config.nbatch, \
                        f"{n} trajectories, {slots} slots, {batches} batches asked for"
                except Exception as e:
                    counts["unreadable"] += 1
                    unreadable.append(f"attempt {attempt} ({kind}, {pace}): {e!r}"[:300])
    finally:
        swapper.close()
    seconds = time.monotonic() - started
    print(f"\nstore race: {counts['attempts']} attempts {kinds} in {seconds:.1f} s; "
          f"{counts['exchanges']} exchanges in {counts['rounds']} swap rounds; "
          f"{counts['succeeded']} writes succeeded, {counts['raised']} raised {errors}; "
          f"{counts['slots']} slots committed; {counts['outside']} attempts changed files "
          f"outside the store ({counts['succeeded_outside']} of them reported success; by "
          f"pace [attempts, successes, outside]: {paces}; through {through}); "
          f"{counts['unreadable']} successes did not read back whole {unreadable[:2]}")
    assert counts["exchanges"] >= 1000, f"the swapper barely ran: {counts}"
    assert counts["slots"] > 0, f"no write got as far as committing a slot: {counts}"
    assert counts["unreadable"] == 0, f"writes that said they succeeded: {unreadable[:3]}"
    assert counts["outside"] == 0, (
        f"{counts['outside']} of {counts['attempts']} writes changed files outside the store "
        f"({counts['succeeded_outside']} of them reported success), through {through}; "
        f"the first: " +
        "; ".join(f"attempt {a} ({k}, {p}, {'succeeded' if ok else 'raised'}): " +
                  ", ".join(f"through {t!r}: {found[:4]}" for t, found in outside)
                  for a, k, p, ok, outside in changes[:3]))
