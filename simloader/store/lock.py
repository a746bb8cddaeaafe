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

import errno
import fcntl
import json
import os
import socket
import stat
import time
import uuid
from typing import Optional

FILE = "simloader.lock"


class StoreLocked(RuntimeError):
    """Another writer holds the store."""


def new_job_id() -> str:
    """A writing job's id (its rank 0 draws it and hands it to the other ranks)."""
    return "job-" + uuid.uuid4().hex[:16]


def holder(root: str) -> Optional[dict]:
    """What the lock file says of its holder (None: empty, never held or released)."""
    try:
        fd = os.open(os.path.join(root, FILE), os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:  # absent, or a link: no holder simloader wrote
        return None
    with os.fdopen(fd, encoding="utf-8", errors="replace") as f:
        text = f.read(1 << 16)
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
        file = os.path.join(self.root, FILE)
        try:
            # never through a link: a lock linked to a file outside the store would empty it
            fd = os.open(file, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o644)
        except OSError as e:
            if e.errno != errno.ELOOP:
                raise
            raise ValueError(f"path: the store's lock {file} is a link, which simloader never "
                             f"makes (it would write through it to a file outside the store); "
                             f"remove it") from None
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise ValueError(f"path: the store's lock {file} is not a regular file; "
                                 f"remove it")
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
