"""One writer job per store: a lock held for the whole `write`.

The lock is an advisory `flock` on the file `simloader.lock` in the store's root, taken by the
writing job's rank 0 (its DataLoader workers are its children and write under it; the other
torchrun ranks join it). A second process that is not of that job is refused at once, with
the holder's host, process id and start time, which the holder writes into the file.

The kernel releases an `flock` when its holder dies, however it dies: a killed writer's lock
is taken over by the next `write` with no timeout to wait out and no stale-lock guess. The
file itself is never removed (removing it would let two processes lock two different files
of the same name). On NFS, `flock` is emulated by `fcntl` locks (NFSv4 and lockd: Linux
since 2.6.12); a file system without locks raises the OSError that says so.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import socket
import time
import uuid
from typing import Optional

FILE = "simloader.lock"


class StoreLocked(RuntimeError):
    """Another writer holds the store."""


def job_id(world: int) -> str:
    """What the ranks of one torchrun job share and another job does not: the rendezvous
    (run id, master address and port, world size); a process of its own otherwise."""
    if world > 1:
        parts = [os.environ.get(k, "") for k in ("TORCHELASTIC_RUN_ID", "MASTER_ADDR",
                                                  "MASTER_PORT")] + [str(world)]
        return "torchrun-" + hashlib.sha256("\0".join(parts).encode()).hexdigest()[:16]
    return "process-" + uuid.uuid4().hex[:16]


def holder(root: str) -> Optional[dict]:
    """What the lock file says of its holder (None: empty, never held or released)."""
    try:
        with open(os.path.join(root, FILE), encoding="utf-8") as f:
            text = f.read()
    except FileNotFoundError:
        return None
    try:
        value = json.loads(text) if text.strip() else None
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def describe(info: Optional[dict]) -> str:
    if not info:
        return "a process that has not written its name yet"
    return (f"process {info.get('pid')} on host {info.get('host')!r}, writing since "
            f"{info.get('started')} (job {info.get('job')})")


class WriterLock:
    """The store's lock, held by this process from `acquire` to `release`."""

    def __init__(self, root: str, job: str):
        self.root, self.job = root, job
        self.fd: Optional[int] = None
        self.took_over: Optional[dict] = None  # a killed writer's entry, found at acquire

    def acquire(self) -> "WriterLock":
        os.makedirs(self.root, exist_ok=True)
        fd = os.open(os.path.join(self.root, FILE), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise StoreLocked(f"path: the store at {self.root!r} is being written by "
                              f"{describe(holder(self.root))}; one job writes a store at a "
                              f"time: wait for it to finish (then writing again resumes "
                              f"or extends it) or write to another path") from None
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        self.took_over = holder(self.root)  # released locks are emptied: a killed holder's
        entry = json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "job": self.job,
                            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}).encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, entry, 0)
        os.fsync(fd)
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.ftruncate(self.fd, 0)  # emptied: the next holder finds no killed writer
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> "WriterLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def check_joined(root: str, job: str, rank: int) -> None:
    """A rank other than 0 writes under its rank 0's lock: refused if another job holds it."""
    info = holder(root)
    if not info or info.get("job") != job:
        raise StoreLocked(f"path: rank {rank} expected the store at {root!r} to be locked by "
                          f"its own job's rank 0, but it is held by {describe(info)}; one "
                          f"job writes a store at a time")
