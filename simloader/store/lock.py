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
from typing import Optional, Union

from simloader.store.folder import StoreFolder

FILE = "simloader.lock"


class StoreLocked(RuntimeError):
    """Another writer holds the store."""


def new_job_id() -> str:
    """A writing job's id (its rank 0 draws it and hands it to the other ranks)."""
    return "job-" + uuid.uuid4().hex[:16]


def holder(root: Union[str, StoreFolder]) -> Optional[dict]:
    """What the lock file says of its holder (None: empty, never held or released)."""
    try:
        if isinstance(root, StoreFolder):
            fd = os.open(FILE, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=root.fd)
        else:
            fd = os.open(os.path.join(root, FILE), os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:  # absent, or a link: no holder simloader wrote
        return None
    try:
        return _read_holder(fd)
    finally:
        os.close(fd)


def describe(info: Optional[dict]) -> str:
    if not info:
        return "a process that has not written its name yet"
    return (f"process {info.get('pid')} on host {info.get('host')!r}, writing since "
            f"{info.get('started')} (job {info.get('job')})")


class WriterLock:
    """The store's lock, held by this process from `acquire` to `release`. `root` is the
    store's folder (a `StoreFolder`, opened by the caller, or a path, opened here)."""

    def __init__(self, root: Union[str, StoreFolder], job: str):
        self.root = root.path if isinstance(root, StoreFolder) else root
        self.folder = root if isinstance(root, StoreFolder) else None
        self.job = job
        self.fd: Optional[int] = None
        self.took_over: Optional[dict] = None  # a killed writer's entry, found at acquire

    def acquire(self) -> "WriterLock":
        folder = self.folder or StoreFolder(self.root, create=True)
        file = os.path.join(self.root, FILE)
        try:
            # never through a link: a lock linked to a file outside the store would empty it
            fd = os.open(FILE, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK |
                         os.O_CLOEXEC, 0o644, dir_fd=folder.fd)
        except OSError as e:
            if e.errno != errno.ELOOP:
                raise
            raise ValueError(f"path: the store's lock {file} is a link, which simloader never "
                             f"makes (it would write through it to a file outside the store); "
                             f"remove it") from None
        finally:
            if self.folder is None:
                folder.close()
        try:
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode):
                raise ValueError(f"path: the store's lock {file} is not a regular file; "
                                 f"remove it")
            if info.st_nlink != 1:
                # a hard link: holding the lock empties the file it shares (another copy's
                # lock, made by `cp -al`, or any file of the user's linked there)
                raise ValueError(f"path: the store's lock {file} has {info.st_nlink} hard "
                                 f"links (a copy of the store made with `cp -al`, or a file "
                                 f"linked there); holding it would empty the file it shares "
                                 f"and lock the other copy's writers out. Remove {file} (a "
                                 f"writer makes a fresh one)")
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
        self.took_over = _read_holder(fd)  # released locks are emptied: a killed holder's
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


def _read_holder(fd: int) -> Optional[dict]:
    text = os.pread(fd, 1 << 16, 0).decode("utf-8", errors="replace")
    try:
        value = json.loads(text) if text.strip() else None
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def check_joined(root: Union[str, StoreFolder], job: str, rank: int) -> None:
    """A rank other than 0 writes under its rank 0's lock: refused if another job holds it."""
    info = holder(root)
    if not info or info.get("job") != job:
        where = root.path if isinstance(root, StoreFolder) else root
        raise StoreLocked(f"path: rank {rank} expected the store at {where!r} to be locked by "
                          f"its own job's rank 0, but it is held by {describe(info)}; one "
                          f"job writes a store at a time")
