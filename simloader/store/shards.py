"""Reading a store's shard files with bounded resources, trusting nothing they say.

An array's metadata (`zarr.json`) is parsed into an `ArrayLayout` and checked against the
store's root (the same `nbatch`, a dtype and codecs simloader writes); a shard is opened only
after its size is checked against that layout (dtype x shape = bytes) and its chunk index
against the file; a link is never followed. Every refusal is a `DamagedStore` that names the
file, the batch slot and what differs.

Open shards are held in one least-recently-used table per process (`OPEN_SHARDS`): a raw
shard is one memory map, a compressed one one file descriptor, and at most `MAX_OPEN` are open
at once however many slots a store has (a shuffled epoch over thousands of slots once ran
out of file descriptors, about 5 per slot, at slot 203 under `ulimit -n 1024`).
"""

from __future__ import annotations

import collections
import dataclasses
import mmap
import os
import secrets
import stat
import threading
from typing import Any, Optional

import numpy as np

from simloader.store.folder import StoreFolder
from simloader.store.zarr_format import (_NO_CHUNK, _ZARR_DTYPES, ATTRIBUTE, DamagedStore,
                                         raw_shard_bytes, shard_key, zstd, blosc)


class StoreReplaced(DamagedStore):
    """The store a reader opened was replaced (or removed) since: its slots would be another
    store's trajectories."""


class OpenedStore:
    """The store a reader opened: its folder (every shard is opened through it, no link
    followed) and its identity (the root's `id`, drawn when the store was made), confirmed
    each time a shard is opened, after it is: a shard opened before the confirmation is of
    the store that still held that identity then (a store is made root first, so a shard of
    a newer store means a newer root). The root is read again only when its file changed
    (another inode, time or size: a growing store rewrites it)."""

    def __init__(self, folder: StoreFolder, identity: Optional[str]):
        self.folder, self.identity = folder, identity
        self._seen: Optional[tuple] = None

    def confirm(self) -> None:
        """Raises `StoreReplaced` unless the store's root still holds its identity."""
        try:
            info = self.folder.stat("zarr.json")
            seen = (info.st_ino, info.st_mtime_ns, info.st_size)
            if seen == self._seen:
                return
            meta = self.folder.read_json("zarr.json")
        except (FileNotFoundError, DamagedStore):
            meta = None
        kept = ((meta or {}).get("attributes") or {}).get(ATTRIBUTE) \
            if isinstance(meta, dict) else None
        if not isinstance(kept, dict) or kept.get("id") != self.identity:
            what = ("removed" if meta is None else "replaced by another store (another "
                    "write(..., replace=True), or a store written anew there)")
            raise StoreReplaced(f"the store at {self.folder.path!r} was {what} since it was "
                                f"opened: its slots no longer hold the trajectories this "
                                f"reader listed. Open it again (StoredDataset(path)) to read "
                                f"what it holds now")
        self._seen = seen

# Open shards per process: each is one map or one descriptor. Small enough to stay far below
# the common `ulimit -n` of 256 to 1024 with DataLoader workers' pipes beside it, large enough
# to hold every array of a window of quasi-random blocks (`order.QuasiRandom`).
MAX_OPEN = 128


@dataclasses.dataclass(frozen=True)
class ArrayLayout:
    """One array's metadata, checked: `ntrajectories x trailing` of `dtype`, sharded per batch
    slot of `nbatch` rows, chunked per trajectory (or per block of camera frames)."""

    path: str  # in the store
    file: str  # its zarr.json, for messages
    shape: tuple
    dtype: np.dtype
    nbatch: int  # rows per shard
    chunk: tuple
    compressed: bool
    shuffled: bool  # blosc (`write(compression="zstd")`), else zstd where compressed
    attributes: dict

    @property
    def trailing(self) -> tuple:
        return self.shape[1:]

    @property
    def empty(self) -> bool:
        return 0 in self.trailing

    @property
    def shard_shape(self) -> tuple:
        return (self.nbatch, *self.trailing)

    @property
    def nchunks(self) -> int:
        return int(np.prod([s // c for s, c in zip(self.shard_shape, self.chunk)]))

    @property
    def raw_bytes(self) -> Optional[int]:
        """A raw shard's file size; None for compressed chunks (any size)."""
        return (None if self.compressed else
                raw_shard_bytes(self.nbatch, self.trailing, self.chunk, self.dtype))

    def shard_name(self, slot: int) -> str:
        """Its shard of `slot`, relative to the store's root."""
        return shard_key(self.path, len(self.trailing), slot)

    def shard_file(self, root: str, slot: int) -> str:
        return os.path.join(root, self.shard_name(slot))

    @classmethod
    def parse(cls, root: str, path: str, meta: Any, nbatch: int) -> "ArrayLayout":
        """Checks `meta` (an array's zarr.json) as simloader writes it, with `nbatch` rows per
        shard; raises DamagedStore naming the file and the field that differs."""
        file = os.path.join(root, path, "zarr.json")

        def refuse(what: str) -> DamagedStore:
            return DamagedStore(f"{file}: {what}; the store's metadata was edited or damaged, "
                                f"or it was not written by simloader.write (read it with zarr)")

        try:
            shape = tuple(int(n) for n in meta["shape"])
            grid = tuple(int(n) for n in meta["chunk_grid"]["configuration"]["chunk_shape"])
            sharding = meta["codecs"][0]
            config = sharding["configuration"]
            chunk = tuple(int(n) for n in config["chunk_shape"])
            inner = [c["name"] for c in config["codecs"]]
            index = [c["name"] for c in config["index_codecs"]]
            data_type = meta["data_type"]
            attributes = meta.get("attributes", {})
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise refuse(f"not the zarr v3 array metadata simloader writes ({e!r} missing or "
                         f"malformed)") from None
        if sharding.get("name") != "sharding_indexed" or config.get("index_location") != "end" \
                or index != ["bytes"] or inner[:1] != ["bytes"] \
                or inner[1:] not in ([], ["zstd"], ["blosc"]):
            raise refuse(f"codecs {meta['codecs']} are not the ones simloader writes")
        dtypes = {v: k for k, v in _ZARR_DTYPES.items()}
        if data_type not in dtypes:
            raise refuse(f"data_type {data_type!r} is not one of {sorted(dtypes)}")
        dtype = np.dtype(dtypes[data_type])
        dtype = dtype.newbyteorder("<") if dtype.itemsize > 1 else dtype
        if not shape or min(shape) < 0 or len(grid) != len(shape) or len(chunk) != len(shape):
            raise refuse(f"shape {list(shape)}, shard shape {list(grid)} and chunk shape "
                         f"{list(chunk)} disagree in rank")
        if grid[0] != nbatch:
            raise refuse(f"shards of {grid[0]} rows, the store's root says nbatch={nbatch}")
        if list(grid[1:]) != [max(1, n) for n in shape[1:]]:
            raise refuse(f"shard shape {list(grid)} does not hold whole trajectories of shape "
                         f"{list(shape[1:])}")
        if chunk[0] != 1 or any(c < 1 or g % c for g, c in zip(grid, chunk)):
            raise refuse(f"chunk shape {list(chunk)} does not divide the shard shape "
                         f"{list(grid)} into trajectories")
        if not isinstance(attributes, dict):
            raise refuse(f"attributes {attributes!r} are not a mapping")
        return cls(path, file, shape, dtype, nbatch, chunk, inner[1:] != [],
                   inner[1:] == ["blosc"], attributes)


class ShardFile:
    """One shard file of one array, checked at open: a raw shard is a memory map (a
    trajectory is a slice of it), a compressed one a descriptor read with `os.pread`."""

    def __init__(self, opened: OpenedStore, layout: ArrayLayout, slot: int,
                 whole: bool = False):
        """`whole`: the shard will be read whole (a block of a quasi-random epoch): its map is
        populated at once (`MAP_POPULATE`: the file read in order and every page mapped),
        instead of one page fault per page touched in shuffled order (cold, that ran at
        0.45M humanoid transitions/s in one process against 0.87M warm)."""
        name = layout.shard_name(slot)
        self.file = file = opened.folder.where(name)
        self.layout, self.slot, self.whole = layout, slot, whole
        self.map: Optional[mmap.mmap] = None
        self.fd: Optional[int] = None
        try:
            fd = opened.folder.open_file(name)
        except FileNotFoundError:
            opened.confirm()  # gone because the store was replaced: say that
            raise DamagedStore(f"{file}: missing: batch slot {slot} is marked written but "
                               f"its shard of {layout.path!r} is gone; calling "
                               f"simloader.write again with the same dataset rewrites it"
                               ) from None
        except DamagedStore:
            opened.confirm()
            raise
        except OSError as e:
            raise DamagedStore(f"{file}: cannot be opened ({e.strerror}) (batch slot "
                               f"{slot})") from None
        try:
            opened.confirm()  # after the open: see `OpenedStore`
            self.rows, self.index = self._open(fd)
        except BaseException:
            os.close(fd)
            raise
        if self.rows is not None:
            os.close(fd)  # the map holds its own descriptor
        else:
            self.fd = fd

    def damaged(self, what: str) -> DamagedStore:
        return DamagedStore(f"{self.file}: {what} (batch slot {self.slot}, array "
                            f"{self.layout.path!r}); calling simloader.write again with the "
                            f"same dataset rewrites the slot")

    def _open(self, fd: int) -> tuple[Optional[np.ndarray], np.ndarray]:
        layout = self.layout
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise self.damaged("not a regular file")
        size, index_bytes = info.st_size, 16 * layout.nchunks
        expected = layout.raw_bytes
        if expected is not None and size != expected:
            raise self.damaged(f"{size} bytes, expected {expected} "
                               f"({'x'.join(map(str, layout.shard_shape))} {layout.dtype} "
                               f"and a chunk index of {index_bytes}): truncated or damaged")
        if size < index_bytes:
            raise self.damaged(f"{size} bytes, shorter than its chunk index ({index_bytes})")
        index = np.frombuffer(os.pread(fd, index_bytes, size - index_bytes),
                              dtype="<u8").reshape(-1, 2)
        if expected is not None:
            length = int(np.prod(layout.chunk)) * layout.dtype.itemsize
            if not (np.array_equal(index[:, 0], np.arange(layout.nchunks) * length) and
                    (index[:, 1] == length).all()):
                raise self.damaged("its chunk index does not describe the rows back to back")
            flags = mmap.MAP_SHARED | (getattr(mmap, "MAP_POPULATE", 0) if self.whole else 0)
            data = mmap.mmap(fd, size - index_bytes, flags=flags, prot=mmap.PROT_READ)
            self.map = data
            # a plain ndarray over the map: np.memmap's Python-level indexing costs more
            # than the small gathers themselves
            return np.ndarray(layout.shard_shape, dtype=layout.dtype, buffer=data), index
        present = index[:, 0] != _NO_CHUNK
        if (index[present, 0] + index[present, 1] > size - index_bytes).any():
            raise self.damaged("its chunk index points past the end of the file")
        return None, index

    def trajectory(self, row: int) -> np.ndarray:
        if self.rows is not None:
            return self.rows[row]
        layout = self.layout
        per = layout.nchunks // layout.nbatch  # chunks per trajectory (frame blocks)
        codec = (None if not layout.compressed else blosc() if layout.shuffled else zstd())
        blocks = []
        for k in range(row * per, (row + 1) * per):
            offset, length = (int(v) for v in self.index[k])
            if offset == _NO_CHUNK:
                blocks.append(np.zeros(layout.chunk[1:], dtype=layout.dtype))
                continue
            data = os.pread(self.fd, length, offset)
            try:
                data = codec.decode(data) if codec is not None else data
                blocks.append(np.frombuffer(data, dtype=layout.dtype).reshape(layout.chunk[1:]))
            except (RuntimeError, ValueError) as e:
                raise self.damaged(f"chunk {k} cannot be decoded ({e})") from None
        return np.concatenate(blocks) if len(blocks) > 1 else blocks[0]

    def close(self) -> None:
        # a map is left to its last view (closing one that a caller still slices raises);
        # our callers copy out of it, so it goes with this object
        self.rows = self.map = None
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def read_ahead(files: list[str]) -> None:
    """Reads `files` in order into the page cache on a background thread (the next window
    of a quasi-random epoch is read from the disk while the workers gather from this one).
    The thread ends with its files: nothing is left running once an epoch ends."""
    threading.Thread(target=_read_through, args=(files,), daemon=True,
                     name="simloader-read-ahead").start()


def _read_through(files: list[str]) -> None:
    buffer = bytearray(8 << 20)  # 8 MiB reads: the disk's sequential pace
    for file in files:
        try:
            with open(file, "rb", buffering=0) as f:
                while f.readinto(buffer):
                    pass
        except OSError:
            pass  # a hint only: the reader names a missing or damaged file itself


class OpenShards:
    """The open shards of this process, least recently used closed first beyond `MAX_OPEN`;
    made anew in a forked child (maps and descriptors are the parent's)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.pid = os.getpid()
        self.table: collections.OrderedDict[tuple[int, int], ShardFile] = \
            collections.OrderedDict()

    def get(self, token: int, layout: ArrayLayout, opened: OpenedStore, slot: int,
            will_need: bool = False) -> ShardFile:
        """The shard of `slot` of the array `token` names (one per `StoredArray`: a path is
        not a key, a store may be written anew at the same path with another layout)."""
        with self.lock:
            if self.pid != os.getpid():
                self.table, self.pid = collections.OrderedDict(), os.getpid()
            key = (token, slot)
            shard = self.table.get(key)
            if shard is not None:
                self.table.move_to_end(key)
                return shard
            while len(self.table) >= MAX_OPEN:
                self.table.popitem(last=False)[1].close()
            shard = self.table[key] = ShardFile(opened, layout, slot, whole=will_need)
        return shard

    def __len__(self) -> int:
        return len(self.table)


OPEN_SHARDS = OpenShards()


class StoredArray:
    """One array of a store, read per trajectory or per batch slot."""

    def __init__(self, opened: OpenedStore, layout: ArrayLayout):
        self.opened, self.layout = opened, layout
        self.dtype, self.trailing = layout.dtype, layout.trailing
        self.shard_shape = layout.shard_shape
        # its shards' key in OPEN_SHARDS: random, so that copies sent to spawned workers
        # never meet another array's key there
        self.token = secrets.randbits(63)

    def trajectory(self, slot: int, row: int) -> np.ndarray:
        if self.layout.empty:
            return np.zeros(self.trailing, dtype=self.dtype)
        return OPEN_SHARDS.get(self.token, self.layout, self.opened, slot).trajectory(row)

    def slot(self, slot: int, will_need: bool = False) -> np.ndarray:
        """All rows of a batch slot (a view of the map where the shard is raw)."""
        if self.layout.empty:
            return np.zeros(self.shard_shape, dtype=self.dtype)
        shard = OPEN_SHARDS.get(self.token, self.layout, self.opened, slot, will_need)
        if shard.rows is not None:
            return shard.rows
        return np.stack([shard.trajectory(r) for r in range(self.shard_shape[0])])
