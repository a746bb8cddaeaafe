"""A store's folder, held open: every file operation of a write is made relative to it.

A check by path and a write by path are two moments: a folder of the store exchanged with a
link between them (`renameat2(RENAME_EXCHANGE)`) would have the writer create, overwrite or
remove files wherever the link points. So a writer opens the store's root folder once, by
the path the user gave (links in that path are the user's own), and reaches every file below
it `openat`-style: each level opened relative to the one above with `O_NOFOLLOW`, files
created with `O_EXCL | O_NOFOLLOW`, renamed and removed relative to their folder's
descriptor. A link met on the way is refused (`StoreChanged`), never followed; a folder
swapped away after it was opened is still the one written (the store's own, wherever it now
lies), never the one put in its place.

Names here are relative to the store's root, "/"-separated ("state/c/3/0/0").
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import stat
import uuid
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, Optional

from simloader.atomic import PARTIAL
from simloader.store.zarr_format import DamagedStore

_DIRECTORY = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | os.O_CLOEXEC
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


class StoreChanged(DamagedStore):
    """A link, or something other than a folder, where the store keeps a folder (someone
    changed the store while it was used): refused, nothing written through it."""


class StoreFolder:
    """The root folder of a store, open by descriptor (`fd`); `path` names it in messages.

    Pickled (to a spawned DataLoader worker) it opens the path again and refuses a folder
    other than the one it held (another device or inode); a forked worker shares the
    descriptor."""

    def __init__(self, path: str, create: bool = False, fd: Optional[int] = None):
        """Opens `path` (made, with its missing parents, where `create`), or takes `fd`, a
        descriptor of it the caller opened (`sub`)."""
        self.path = path
        if fd is None:
            if create:
                os.makedirs(path, exist_ok=True)
            fd = os.open(path, _DIRECTORY)
        self.fd = fd
        info = os.fstat(self.fd)
        if not stat.S_ISDIR(info.st_mode):
            os.close(self.fd)
            raise NotADirectoryError(errno.ENOTDIR, "not a folder", path)
        self.ident = (info.st_dev, info.st_ino)

    def __getstate__(self) -> dict:
        return {"path": self.path, "ident": self.ident}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"])
        if self.ident != state["ident"]:
            self.close()
            raise StoreChanged(f"{state['path']}: not the folder the store was opened in (it "
                               f"was moved or replaced meanwhile); nothing was written to it")

    def close(self) -> None:
        if getattr(self, "fd", -1) >= 0:
            os.close(self.fd)
            self.fd = -1

    def __del__(self) -> None:
        try:
            self.close()
        except OSError:
            pass

    def __enter__(self) -> "StoreFolder":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def sub(self, name: str, create: bool = False) -> "StoreFolder":
        """Folder `name` below this one as a `StoreFolder` of its own (reached without
        following a link)."""
        return StoreFolder(self.where(name), fd=self.open_directory(name, create))

    def where(self, name: str) -> str:
        """The path of `name` for a message."""
        return os.path.join(self.path, *name.split("/")) if name else self.path

    # ------------------------------------------------------------------ folders

    @contextlib.contextmanager
    def directory(self, name: str, create: bool = False) -> Iterator[int]:
        """The descriptor of folder `name` (the root for ""), reached level by level without
        following a link; `create` makes the missing levels."""
        fd = self.open_directory(name, create)
        try:
            yield fd
        finally:
            os.close(fd)

    def open_directory(self, name: str, create: bool = False) -> int:
        """As `directory`, a descriptor the caller closes."""
        fd = os.dup(self.fd)
        done: list[str] = []
        try:
            for part in _parts(name):
                below = self._open_below(fd, part, "/".join(done + [part]), create)
                os.close(fd)
                fd = below
                done.append(part)
        except BaseException:
            os.close(fd)
            raise
        return fd

    def _open_below(self, fd: int, part: str, name: str, create: bool) -> int:
        """Folder `part` of the folder `fd` (`name` from the root), made first where
        `create` and missing."""
        try:
            return os.open(part, _DIRECTORY | _NOFOLLOW, dir_fd=fd)
        except FileNotFoundError:
            if not create:
                raise FileNotFoundError(errno.ENOENT, "no such folder",
                                        self.where(name)) from None
        except OSError as e:
            if e.errno not in (errno.ELOOP, errno.ENOTDIR):
                raise
            raise self.changed(name) from None
        try:
            os.mkdir(part, 0o777, dir_fd=fd)
        except FileExistsError:
            pass
        return self._open_below(fd, part, name, create=False)

    def changed(self, name: str) -> StoreChanged:
        return StoreChanged(f"{self.where(name)}: a link, or not a folder, where the store at "
                            f"{self.path!r} keeps a folder (put there, or swapped in while "
                            f"simloader used the store). simloader never follows a link in a "
                            f"store (one could lead outside it), so nothing was read or "
                            f"written through it: remove the link, or put the store's own "
                            f"folder back")

    def entries(self, name: str = "") -> list[tuple[str, str, int]]:
        """(entry, kind, size) of folder `name`'s entries, kind one of "folder", "file",
        "link", "other", or "gone" (removed while listed); links are not followed."""
        with self.directory(name) as fd:
            out = []
            with os.scandir(fd) as listing:
                for entry in listing:
                    try:
                        info = entry.stat(follow_symlinks=False)
                    except FileNotFoundError:
                        out.append((entry.name, "gone", 0))
                        continue
                    out.append((entry.name, _mode_kind(info.st_mode), info.st_size))
        return out

    def kind(self, name: str) -> Optional[str]:
        """"folder", "file", "link", "other", or None where nothing is (or a level above is
        missing); never follows a link."""
        head, _, last = name.rpartition("/")
        try:
            with self.directory(head) as fd:
                info = os.stat(last, dir_fd=fd, follow_symlinks=False)
        except FileNotFoundError:
            return None
        return _mode_kind(info.st_mode)

    def stat(self, name: str) -> os.stat_result:
        head, _, last = name.rpartition("/")
        with self.directory(head) as fd:
            return os.stat(last, dir_fd=fd, follow_symlinks=False)

    def make_directories(self, name: str) -> None:
        with self.directory(name, create=True):
            pass

    def sync(self, names: Iterable[str]) -> None:
        """fsyncs folders `names` (deepest first), so the names renamed and made in them
        survive a power loss; a folder already gone is skipped."""
        for name in sorted(set(names), key=lambda n: (-n.count("/"), n)):
            try:
                fd = self.open_directory(name)
            except FileNotFoundError:
                continue
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    # ------------------------------------------------------------------ files

    def open_file(self, name: str) -> int:
        """A descriptor of regular file `name`, read-only, no link followed at any level
        (`FileNotFoundError` when absent; `StoreChanged` for a link or a non-file)."""
        head, _, last = name.rpartition("/")
        with self.directory(head) as directory:
            try:
                fd = os.open(last, os.O_RDONLY | _NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC,
                             dir_fd=directory)
            except OSError as e:
                if e.errno in (errno.ELOOP, errno.ENOTDIR):
                    raise self.changed(name) from None
                if e.errno == errno.ENOENT:
                    raise FileNotFoundError(errno.ENOENT, "no such file",
                                            self.where(name)) from None
                raise
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise StoreChanged(f"{self.where(name)}: not a regular file")
        return fd

    def read(self, name: str, limit: int = 1 << 26) -> bytes:
        fd = self.open_file(name)
        with os.fdopen(fd, "rb") as f:
            return f.read(limit)

    def read_json(self, name: str) -> Optional[dict]:
        """A metadata file (None if absent); one that is not JSON is named."""
        try:
            data = self.read(name)
        except FileNotFoundError:
            return None
        try:
            return json.loads(data.decode("utf-8"))
        except (ValueError, UnicodeDecodeError, RecursionError) as e:
            raise DamagedStore(f"{self.where(name)}: not valid JSON ({type(e).__name__}: "
                               f"{str(e)[:200]}); the store's metadata was edited or "
                               f"damaged") from None

    def stage(self, name: str, parts: Sequence[Any]) -> "Staged":
        """Writes `parts` to a new temporary file beside `name` (NAME.<32 hex>.partial,
        created exclusively, no link followed), its folders made as needed. The caller
        `fsync`s and `commit`s it (or `discard`s it)."""
        head, _, last = name.rpartition("/")
        directory = self.open_directory(head, create=True)
        temporary = f"{last}.{uuid.uuid4().hex}{PARTIAL}"
        try:
            fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW |
                         os.O_CLOEXEC, 0o644, dir_fd=directory)
        except BaseException:
            os.close(directory)
            raise
        staged = Staged(directory, fd, temporary, last)
        try:
            with os.fdopen(os.dup(fd), "wb", closefd=True) as f:
                for part in parts:
                    f.write(part)
        except BaseException:
            staged.discard()
            raise
        return staged

    def write(self, name: str, parts: Sequence[Any], durable: bool = False) -> None:
        """Writes file `name` whole or not at all (a temporary renamed over it); `durable`
        fsyncs it before the rename (its folder is the caller's to sync)."""
        staged = self.stage(name, parts)
        try:
            if durable:
                staged.fsync()
            staged.commit()
        except BaseException:
            staged.discard()
            raise

    def write_json(self, name: str, value: dict, durable: bool = False) -> None:
        self.write(name, [json.dumps(value, indent=2, sort_keys=True).encode()], durable)

    def unlink(self, name: str, missing_ok: bool = True) -> None:
        head, _, last = name.rpartition("/")
        try:
            with self.directory(head) as fd:
                os.unlink(last, dir_fd=fd)
        except FileNotFoundError:
            if not missing_ok:
                raise

    def remove_tree(self, name: str) -> None:
        """Removes folder `name` and everything in it, descending by descriptors: a link
        inside is removed itself, never followed."""
        head, _, last = name.rpartition("/")
        with self.directory(head) as parent:
            _remove_below(parent, last)


class Staged:
    """A temporary file written beside its name, its folder held open until it is renamed
    (so it is renamed in the folder it was written in, whatever happened to paths since)."""

    def __init__(self, directory: int, fd: int, temporary: str, last: str):
        self.directory, self.fd, self.temporary, self.last = directory, fd, temporary, last

    def fsync(self) -> None:
        os.fsync(self.fd)

    def commit(self) -> None:
        """Renames the temporary over its name and closes it."""
        os.replace(self.temporary, self.last, src_dir_fd=self.directory,
                   dst_dir_fd=self.directory)
        self._close()

    def discard(self) -> None:
        """Removes the temporary, unless it was renamed already."""
        if self.directory < 0:
            return
        try:
            os.unlink(self.temporary, dir_fd=self.directory)
        except OSError:
            pass
        self._close()

    def _close(self) -> None:
        for fd in (self.fd, self.directory):
            if fd >= 0:
                os.close(fd)
        self.fd = self.directory = -1


def folders_above(name: str, top: str = "") -> list[str]:
    """The folders from `name`'s own up to and including `top` (which holds it): those whose
    entries a new file `name` (and the folders made for it) changed."""
    out = []
    head = name.rpartition("/")[0]
    while True:
        out.append(head)
        if head == top or not head:
            return out
        head = head.rpartition("/")[0]


def _parts(name: str) -> list[str]:
    parts = [p for p in name.split("/") if p not in ("", ".")]
    if ".." in parts:
        raise ValueError(f"store: the name {name!r} leads outside the store")
    return parts


def _mode_kind(mode: int) -> str:
    if stat.S_ISLNK(mode):
        return "link"
    if stat.S_ISDIR(mode):
        return "folder"
    return "file" if stat.S_ISREG(mode) else "other"


def _remove_below(parent: int, name: str, depth: int = 0) -> None:
    if depth > 64:
        raise StoreChanged(f"{name}: folders nested deeper than any store simloader writes")
    try:
        info = os.stat(name, dir_fd=parent, follow_symlinks=False)
    except FileNotFoundError:
        return
    try:
        if not stat.S_ISDIR(info.st_mode):
            os.unlink(name, dir_fd=parent)
            return
        fd = os.open(name, _DIRECTORY | _NOFOLLOW, dir_fd=parent)
    except FileNotFoundError:
        return
    except OSError as e:
        if e.errno not in (errno.EISDIR, errno.ENOTDIR, errno.ELOOP):
            raise
        raise StoreChanged(f"{name}: swapped for another kind of entry while it was "
                           f"removed; nothing outside the store was touched: remove "
                           f"what is not the store's and write again") from None
    try:
        opened = os.fstat(fd)
        if (opened.st_dev, opened.st_ino) != (info.st_dev, info.st_ino):
            raise StoreChanged(f"{name}: changed while it was removed")
        with os.scandir(fd) as listing:
            names = [e.name for e in listing]
        for entry in names:
            _remove_below(fd, entry, depth + 1)
    finally:
        os.close(fd)
    try:
        os.rmdir(name, dir_fd=parent)
    except NotADirectoryError:
        raise StoreChanged(f"{name}: swapped for a file or a link while it was removed; "
                           f"nothing outside the store was touched") from None
