"""The on-disk format of a store: its arrays, their shard files, written and read.

The store is a zarr v3 group that any zarr client reads (zarr-python, xarray, dask,
tensorstore). Every batch key is an array `ntrajectories x ...` (the batch's own trailing
shape and dtype; `params` keys under `params/`, camera images under `camera/NAME/`), and
`provenance/` holds, per trajectory, the rank, batch index and row that address it in the
seeded stream, and per batch slot whether it is complete (`provenance/written`). The root's
attribute `simloader` holds the configuration (the resume fingerprint and the dataset's
description), the seed and the library versions.

Layout, chosen for writers that never coordinate and readers that never decode twice:

- Batch slot `s` (rank `r` of `W`, batch index `i`, `s = i * W + r`) owns rows
  `s * nbatch ...` of every array, which are one zarr shard per array: one file, written whole
  by one writer, to a temporary name and renamed (a killed writer leaves no torn file).
- Inside a shard every trajectory is its own chunk (camera images: a block of frames), so a
  reader fetches one trajectory without reading its neighbours. Floating point chunks are
  stored raw: MuJoCo's float64 states compress by about 1.13x with zstd at 87 MB/s per core,
  which would cost more generation throughput than the disk it saves; integer and boolean
  chunks of 4 KiB or more (images, segmentation) are compressed with zstd.
- `provenance/written[s]` is written last, so a reader sees complete slots only, and a resumed
  `write` redoes exactly the slots that were not completed.

A shard is written by `write_shard` in zarr's sharding format (inner chunks in C order,
then the index of (offset, length) pairs; no checksum), and read back by `StoredDataset` by
memory-mapping raw shards (a trajectory is a slice of the file) or decoding compressed chunks;
the tests read every store through zarr-python as well.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterator, Mapping
from typing import Any, Optional

import numpy as np
import torch

from simloader.atomic import atomic_write

from simloader import sharding

FORMAT = 1  # of the `simloader` attribute and the layout below it
ATTRIBUTE = "simloader"
PROVENANCE = ("rank", "batch", "row", "num_workers")
_COMPRESS_MIN_BYTES = 4096
_IMAGE_CHUNK_BYTES = 1 << 20  # camera frames per chunk: a block of about 1 MiB
_NO_CHUNK = 2**64 - 1  # zarr's index entry of an absent chunk

# --------------------------------------------------------------------------- the layout

@dataclasses.dataclass(frozen=True)
class ArraySpec:
    """One stored array: `ntrajectories x trailing`, sharded per batch slot of `nbatch` rows,
    one chunk per trajectory (or per block of `chunk_frames` camera frames)."""

    name: str  # path in the store ("state", "camera/top/rgb", "params/body_mass[pole]")
    dtype: np.dtype
    trailing: tuple
    nbatch: int
    chunk_frames: Optional[int] = None  # images: frames per chunk; None: all
    compressed: bool = False

    @property
    def chunk(self) -> tuple:
        trailing = self.trailing
        if self.chunk_frames is not None:
            trailing = (self.chunk_frames, *trailing[1:])
        return (1, *(max(1, n) for n in trailing))  # zarr's chunks have no empty side

    @property
    def empty(self) -> bool:
        """No values (a model without sensors records `sensordata` of width 0): the array's
        metadata alone holds it, with no shard files."""
        return 0 in self.trailing

    def metadata(self, ntrajectories: int) -> dict:
        byte_order = ({"name": "bytes", "configuration": {"endian": "little"}}
                      if self.dtype.itemsize > 1 else {"name": "bytes"})
        inner = [byte_order] + ([{"name": "zstd", "configuration": {"level": 1,
                                                                    "checksum": False}}]
                                if self.compressed else [])
        return {
            "zarr_format": 3, "node_type": "array",
            "shape": [ntrajectories, *self.trailing],
            "data_type": _ZARR_DTYPES[self.dtype.str.lstrip("<>|=")],
            "chunk_grid": {"name": "regular", "configuration": {
                "chunk_shape": [self.nbatch, *(max(1, n) for n in self.trailing)]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": False if self.dtype == np.bool_ else 0,
            "codecs": [{"name": "sharding_indexed", "configuration": {
                "chunk_shape": list(self.chunk), "codecs": inner,
                "index_codecs": [{"name": "bytes", "configuration": {"endian": "little"}}],
                "index_location": "end"}}],
            "attributes": {},
            "dimension_names": ["trajectory"] + [None] * len(self.trailing),
        }

    def shard_key(self, slot: int) -> str:
        return shard_key(self.name, len(self.trailing), slot)


def shard_key(name: str, ntrailing: int, slot: int) -> str:
    """The file of array `name`'s shard of batch slot `slot` (zarr's default chunk keys)."""
    return "/".join([name, "c", str(slot)] + ["0"] * ntrailing)


_ZARR_DTYPES = {"b1": "bool", "u1": "uint8", "i1": "int8", "i2": "int16", "i4": "int32",
                "i8": "int64", "u2": "uint16", "u4": "uint32", "u8": "uint64",
                "f2": "float16", "f4": "float32", "f8": "float64"}


def leaves(batch: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(store name, tensor) of every tensor of a batch; `params` is a dict of tensors."""
    for key, value in batch.items():
        if isinstance(value, Mapping):
            yield from leaves(value, prefix + key + "/")
        else:
            yield prefix + key, value


def safe_name(name: str) -> str:
    """A batch key as a zarr path: its "/" are groups; other characters are kept except a
    leading "__" (reserved by zarr)."""
    return "/".join(("_" + p[2:] if p.startswith("__") else p) for p in name.split("/"))


def specs_of(batch: Mapping[str, Any], nbatch: int) -> list[ArraySpec]:
    """The stored arrays of a batch: every tensor key, `policy/version` (one per batch) made
    one per trajectory, and the provenance arrays."""
    specs = []
    for name, value in leaves(batch):
        if isinstance(value, torch.Tensor):  # shape and dtype, without a copy off the GPU
            shape = tuple(value.shape)
            dtype = torch.empty((), dtype=value.dtype).numpy().dtype
        else:
            array = np.asarray(value)
            shape, dtype = array.shape, array.dtype
        trailing = tuple(shape[1:]) if shape and shape[0] == nbatch else ()
        chunk_frames = None
        if name.startswith("camera/") and len(trailing) >= 3:  # nframes x height x width ...
            frame_bytes = int(np.prod(trailing[1:])) * dtype.itemsize
            chunk_frames = largest_divisor(trailing[0], max(1, _IMAGE_CHUNK_BYTES // frame_bytes))
        chunk_bytes = (int(np.prod(trailing)) * dtype.itemsize if chunk_frames is None else
                       chunk_frames * int(np.prod(trailing[1:])) * dtype.itemsize)
        compressed = dtype.kind in "biu" and chunk_bytes >= _COMPRESS_MIN_BYTES
        specs.append(ArraySpec(safe_name(name), dtype, trailing, nbatch, chunk_frames, compressed))
    specs += [ArraySpec("provenance/" + p, np.dtype(np.int64), (), nbatch) for p in PROVENANCE]
    return specs


def largest_divisor(n: int, most: int) -> int:
    return max(d for d in range(1, min(n, most) + 1) if n % d == 0)


WRITTEN = ArraySpec("provenance/written", np.dtype(np.bool_), (), 1)

# --------------------------------------------------------------------------- files

def write_json(path: str, value: dict) -> None:
    atomic_write(path, [json.dumps(value, indent=2, sort_keys=True).encode()])


def read_json(path: str) -> Optional[dict]:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        return None


def zstd():
    try:
        from numcodecs import Zstd
    except ImportError:
        raise ImportError("simloader.write: compressed arrays (images) need numcodecs: "
                          "pip install 'simloader[zarr]'") from None
    return Zstd(level=1)


_POOL: Optional[tuple[int, Any]] = None


def _encoders():
    """Threads that compress chunks (zstd releases the GIL): camera images compress at about
    300 MB/s per core, a GPU renders them faster. One pool per process (a forked worker's
    copy of the parent's pool has no threads)."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid():
        from concurrent.futures import ThreadPoolExecutor
        _POOL = (os.getpid(), ThreadPoolExecutor(sharding.available_cpus(),
                                                 thread_name_prefix="simloader-zstd"))
    return _POOL[1]


def write_shard(root: str, spec: ArraySpec, slot: int, rows: np.ndarray) -> None:
    """One batch slot of one array, in zarr's sharding format: the inner chunks in C order of
    the chunk grid, then one (offset, length) pair of little-endian uint64 per chunk."""
    if spec.empty:
        return
    rows = np.ascontiguousarray(rows, dtype=spec.dtype.newbyteorder("<"))
    if spec.chunk_frames is None:
        chunks = [rows] if not spec.compressed else [rows[i] for i in range(len(rows))]
    else:  # camera frames: (trajectory, frame block) in C order
        f = spec.chunk_frames
        chunks = [rows[i, j:j + f] for i in range(len(rows)) for j in range(0, rows.shape[1], f)]
    if spec.compressed:
        codec = zstd()
        parts = list(_encoders().map(lambda c: codec.encode(np.ascontiguousarray(c)), chunks))
        lengths = [len(p) for p in parts]
    else:  # raw: every trajectory's chunk is its rows, back to back
        parts = [memoryview(rows).cast("B")]
        size = rows[0].nbytes if len(rows) else 0
        lengths = [size] * len(rows) if spec.chunk_frames is None else [c.nbytes for c in chunks]
    offsets = np.concatenate([[0], np.cumsum(lengths[:-1])]).astype("<u8") if lengths else []
    index = np.stack([np.asarray(offsets, dtype="<u8"), np.asarray(lengths, dtype="<u8")],
                     axis=1)
    atomic_write(os.path.join(root, spec.shard_key(slot)), [*parts, index.tobytes()])


# --------------------------------------------------------------------------- reading

class ShardFile:
    """One shard file of one array: a trajectory's chunks, read by memory map (raw chunks
    laid back to back) or decoded one by one (compressed)."""

    def __init__(self, file: str, spec_shape: tuple, chunk: tuple, dtype: np.dtype,
                 compressed: bool):
        nchunks = int(np.prod([s // c for s, c in zip(spec_shape, chunk)]))
        self.chunk, self.dtype, self.compressed = chunk, dtype, compressed
        self.grid = tuple(s // c for s, c in zip(spec_shape, chunk))
        with open(file, "rb") as f:
            f.seek(-16 * nchunks, os.SEEK_END)
            self.index = np.frombuffer(f.read(16 * nchunks), dtype="<u8").reshape(-1, 2)
        self.file = file
        raw = (not compressed and
               np.array_equal(self.index[:, 0], np.arange(nchunks) * self.index[0, 1]) and
               (self.index[:, 1] == np.prod(chunk) * dtype.itemsize).all())
        # a plain ndarray over the map: np.memmap's Python-level indexing costs more than
        # the small gathers themselves
        self.rows = (np.memmap(file, dtype=dtype, mode="r", shape=spec_shape).view(np.ndarray)
                     if raw else None)

    def trajectory(self, row: int) -> np.ndarray:
        if self.rows is not None:
            return self.rows[row]
        per = int(np.prod(self.grid[1:]))  # chunks per trajectory (frame blocks)
        codec = zstd() if self.compressed else None
        blocks = []
        with open(self.file, "rb") as f:
            for k in range(row * per, (row + 1) * per):
                offset, length = (int(v) for v in self.index[k])
                if offset == _NO_CHUNK:
                    blocks.append(np.zeros(self.chunk[1:], dtype=self.dtype))
                    continue
                f.seek(offset)
                data = f.read(length)
                data = codec.decode(data) if codec is not None else data
                blocks.append(np.frombuffer(data, dtype=self.dtype).reshape(self.chunk[1:]))
        return np.concatenate(blocks) if len(blocks) > 1 else blocks[0]


class StoredArray:
    def __init__(self, root: str, name: str, meta: dict):
        self.root, self.name = root, name
        sharding_codec = meta["codecs"][0]
        if sharding_codec["name"] != "sharding_indexed" or \
                sharding_codec["configuration"]["index_location"] != "end" or \
                [c["name"] for c in sharding_codec["configuration"]["index_codecs"]] != ["bytes"]:
            raise ValueError(f"{name}: not a store written by simloader.write (codecs "
                             f"{meta['codecs']}); read it with zarr")
        inner = [c["name"] for c in sharding_codec["configuration"]["codecs"]]
        self.compressed = inner[1:] == ["zstd"]
        self.shard_shape = tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
        self.chunk = tuple(sharding_codec["configuration"]["chunk_shape"])
        dtype = {v: k for k, v in _ZARR_DTYPES.items()}[meta["data_type"]]
        self.dtype = np.dtype(dtype).newbyteorder("<") if np.dtype(dtype).itemsize > 1 \
            else np.dtype(dtype)
        self.trailing = tuple(meta["shape"][1:])
        self._shards: dict[int, ShardFile] = {}

    def _shard(self, slot: int) -> ShardFile:
        shard = self._shards.get(slot)
        if shard is None:
            key = shard_key(self.name, len(self.trailing), slot)
            shard = self._shards[slot] = ShardFile(os.path.join(self.root, key),
                                                   self.shard_shape, self.chunk, self.dtype,
                                                   self.compressed)
        return shard

    def trajectory(self, slot: int, row: int) -> np.ndarray:
        if 0 in self.trailing:
            return np.zeros(self.trailing, dtype=self.dtype)
        return self._shard(slot).trajectory(row)

    def slot(self, slot: int) -> np.ndarray:
        """All rows of a batch slot (a memory map where the shard is raw)."""
        if 0 in self.trailing:
            return np.zeros(self.shard_shape[:1] + self.trailing, dtype=self.dtype)
        shard = self._shard(slot)
        if shard.rows is not None:
            return shard.rows
        return np.stack([shard.trajectory(r) for r in range(self.shard_shape[0])])


def list_arrays(path: str) -> dict[str, dict]:
    """Every array of the store below its root: {name: zarr metadata}."""
    out = {}
    for directory, subdirs, files in os.walk(path):
        subdirs[:] = [d for d in subdirs if d != "c"]  # chunk folders hold no metadata
        if "zarr.json" in files and directory != path:
            meta = read_json(os.path.join(directory, "zarr.json"))
            if meta.get("node_type") == "array":
                out[os.path.relpath(directory, path).replace(os.sep, "/")] = meta
    return out


def written_slots(path: str, nslots: int) -> np.ndarray:
    """Which batch slots are complete (bool per slot)."""
    out = np.zeros(nslots, dtype=bool)
    for s in range(nslots):
        shard = os.path.join(path, WRITTEN.shard_key(s))
        try:
            with open(shard, "rb") as f:
                out[s] = f.read(1) == b"\x01"
        except FileNotFoundError:
            pass
    return out
