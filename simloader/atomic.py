"""Files written whole or not at all: a reader, a resumed writer or a later process sees the
whole file or none of it, never a part left by a killed process or a full disk; and, where
asked, durable: on the disk before the call returns, as SQLite and git commit (the file
fsync'd before its rename, then the directories that name it)."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterable, Sequence
from typing import Any

PARTIAL = ".partial"  # the suffix of a file being written (a killed writer may leave one)


def atomic_write(path: str, parts: Sequence[Any], durable: bool = False) -> None:
    """Writes `parts` (bytes-like) to `path` through a temporary file renamed over it: a
    reader or a resumed writer sees the whole file or none of it. `durable=True` also
    fsyncs the file before the rename (a power loss after the rename cannot leave it empty);
    the caller fsyncs the directories (`sync_directories`) before it records the file as
    committed, once for all the files of a commit."""
    temporary = write_temporary(path, parts)
    try:
        if durable:
            fsync_file(temporary)
        os.replace(temporary, path)
    except BaseException:
        discard(temporary)
        raise


def write_temporary(path: str, parts: Sequence[Any]) -> str:
    """Writes `parts` to a new temporary name beside `path` (NAME.<32 hex>.partial, which a
    resumed writer removes) and returns that name. The caller makes it durable
    (`fsync_file`) and renames it over `path` (`os.replace`): the store's write pipeline
    does so for all of a slot's files at once."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    temporary = f"{path}.{uuid.uuid4().hex}{PARTIAL}"
    try:
        with open(temporary, "wb") as f:
            for part in parts:
                f.write(part)
    except BaseException:
        discard(temporary)
        raise
    return temporary


def fsync_file(path: str) -> None:
    """fsyncs a written file's data and size (its name is the directory's: `sync_directories`)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def discard(path: str) -> None:
    """Removes a temporary file, if it is there."""
    try:
        os.unlink(path)
    except OSError:
        pass


def sync_directories(directories: Iterable[str]) -> None:
    """fsyncs each directory, so the names of the files renamed into it (and of the
    directories made in it) survive a power loss."""
    for directory in sorted(set(directories), key=len, reverse=True):  # deepest first
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
