"""The on-disk format of a store: its arrays, their shard files, written and read.

The store is a zarr v3 group that any zarr client reads (zarr-python, xarray, dask,
tensorstore). Every batch key is an array `ntrajectories x ...` (the batch's own trailing
shape and dtype; `params` keys under `params/`, camera images under `camera/NAME/`), and
`provenance/` holds, per trajectory, the rank, batch index and row that address it in the
seeded stream, and per batch slot whether it is complete (`provenance/written`). The root's
attribute `simloader` holds the configuration (its identity, `identity.fingerprint`, and the
dataset's description), the seed and the library versions.

Layout, chosen for writers that never coordinate and readers that never decode twice:

- Batch slot `s` (rank `r` of `W`, batch index `i`, `s = i * W + r`) owns rows
  `s * nbatch ...` of every array, which are one zarr shard per array: one file, written whole
  by one writer, to a temporary name and renamed (a killed writer leaves no torn file).
- Inside a shard every trajectory is its own chunk (camera images: a block of frames), so a
  reader fetches one trajectory without reading its neighbours. Floating point chunks are
  stored raw by default: MuJoCo's states compress by 1.05-1.4x, which costs more CPU than a
  fast disk saves; `write(compression="zstd")` compresses them with zarr's blosc codec (byte
  shuffle, zstd). Integer and boolean chunks of 4 KiB or more (images, segmentation) are
  compressed with zstd.
- A slot is committed as SQLite and git commit (`simloader.store.pipeline`): every shard file
  fsync'd and renamed, the directories that name them fsync'd, then `provenance/checksum[s]`
  (each shard's size and CRC-32, in the order of that array's attribute `arrays`), then
  `provenance/written[s]` last. A reader sees complete slots only; a resumed `write` checks
  every committed slot against its checksums and redoes the missing and the damaged ones.
- Array paths come from batch keys, and batch keys from the model (sensor, camera and body
  names) and the user (policy extras): each part is percent-encoded (`store_path`), so no
  name can make a path outside the store, and the key itself is kept in the array's
  attribute `key`.

A shard is encoded by `encode_shard` in zarr's sharding format (inner chunks in C order,
then the index of (offset, length) pairs), and read back by `simloader.store.shards`; the
tests read every store through zarr-python as well.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import threading
import time
import zlib
from collections.abc import Mapping
from typing import Any, Optional
from urllib.parse import unquote

import numpy as np
import torch

from simloader import threads
from simloader.batch import flat

FORMAT = 1  # of the `simloader` attribute and the layout below it
ATTRIBUTE = "simloader"
# the root attribute's "kind" of a mixture's store (one store per task under tasks/), which
# `simloader.open_store` opens as a `StoredMixture`
MIXTURE_KIND = "mixture"
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
    shuffled: bool = False  # compressed by blosc's zstd after a byte shuffle (`compression=`)
    attributes: tuple = ()  # (name, value) pairs: the array's zarr attributes

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
        inner = [byte_order] + ([] if not self.compressed else
                                [_blosc_codec(self.dtype.itemsize)] if self.shuffled else
                                [{"name": "zstd", "configuration": {"level": 1,
                                                                    "checksum": False}}])
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
            "attributes": dict(self.attributes),
            "dimension_names": ["trajectory"] + [None] * len(self.trailing),
        }

    def shard_key(self, slot: int) -> str:
        return shard_key(self.name, len(self.trailing), slot)


def _blosc_codec(typesize: int) -> dict:
    """zarr v3's blosc codec as `compression="zstd"` writes it: zstd level 1 over the bytes
    shuffled by their place in each value (a float's exponent bytes side by side)."""
    return {"name": "blosc", "configuration": {"cname": "zstd", "clevel": 1,
                                               "shuffle": "shuffle", "typesize": typesize,
                                               "blocksize": 0}}


def raw_shard_bytes(nbatch: int, trailing: tuple, chunk: tuple, dtype: np.dtype) -> int:
    """The size of a raw shard's file: its rows, then the chunk index."""
    shape = (nbatch, *trailing)
    nchunks = int(np.prod([s // c for s, c in zip(shape, chunk)]))
    return int(np.prod(shape, dtype=np.int64)) * dtype.itemsize + 16 * nchunks


def shard_key(name: str, ntrailing: int, slot: int) -> str:
    """The file of array `name`'s shard of batch slot `slot` (zarr's default chunk keys)."""
    return "/".join([name, "c", str(slot)] + ["0"] * ntrailing)


_ZARR_DTYPES = {"b1": "bool", "u1": "uint8", "i1": "int8", "i2": "int16", "i4": "int32",
                "i8": "int64", "u2": "uint16", "u4": "uint32", "u8": "uint64",
                "f2": "float16", "f4": "float32", "f8": "float64"}


# characters kept as they are in a part of an array's path; the others are percent-encoded
_PLAIN = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_-.:[]()+,=@")
_GROUPS = ("params", "policy", "provenance")  # KEY/NAME: a group, then one encoded part
_MAX_PART = 200  # bytes: file systems refuse names past 255


def store_path(key: str) -> str:
    """The path in the store of batch key `key`: "/" separates groups only where simloader
    makes them ("camera/NAME/KIND", "params/NAME", "policy/NAME"); every name from a model
    or a user is one percent-encoded part, so "..", "/" and other characters never leave
    the array's directory. Readable keys ("state", "sensor:touch") are unchanged."""
    head, _, rest = key.partition("/")
    if head == "camera" and rest.count("/") >= 1:
        name, _, kind = rest.rpartition("/")
        parts = [head, name, kind]
    elif head in _GROUPS and rest:
        parts = [head, rest]
    else:
        parts = [key]
    return "/".join(_encode_part(p, key) for p in parts)


def batch_key(path: str, meta: Mapping[str, Any]) -> str:
    """The batch key of the array at `path`: its attribute `key`, or for a store written
    before the attribute existed, its path decoded."""
    key = meta.get("attributes", {}).get("key")
    return key if isinstance(key, str) else "/".join(unquote(p) for p in path.split("/"))


def store_part(name: str) -> str:
    """The folder name of `name` as one part, whatever it holds ("/" included): a mixture's
    task name, so that no task's store lies inside another's."""
    return _encode_part(name, name)


def _encode_part(part: str, key: str) -> str:
    if not part:
        raise ValueError(f"batch key {key!r}: an empty name cannot be stored")
    out = "".join(c if c in _PLAIN else "".join(f"%{b:02X}" for b in c.encode())
                  for c in part)
    if out.startswith("."):  # ".", ".." and hidden files
        out = "%2E" + out[1:]
    if out.startswith("__"):  # reserved by zarr
        out = "%5F" + out[1:]
    if len(out.encode()) > _MAX_PART:  # the key itself stays in the array's attribute
        out = out[:_MAX_PART - 17] + "~" + hashlib.sha256(part.encode()).hexdigest()[:16]
    return out


COMPRESSIONS = (None, "zstd")  # `write(compression=)`: of the arrays stored raw by default


def specs_of(batch: Mapping[str, Any], nbatch: int,
             compression: Optional[str] = None) -> list[ArraySpec]:
    """The stored arrays of a batch: every tensor key, `policy/version` (one per batch) made
    one per trajectory, and the provenance arrays. Integer and boolean chunks of 4 KiB or more
    (images) are compressed with zstd; the others are raw unless `compression="zstd"`, which
    compresses every chunk of 4 KiB or more (states: byte shuffle, then zstd)."""
    specs = []
    for name, value in flat(batch).items():
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
        large = chunk_bytes >= _COMPRESS_MIN_BYTES
        compressed = dtype.kind in "biu" and large
        shuffled = not compressed and large and compression == "zstd"
        specs.append(ArraySpec(store_path(name), dtype, trailing, nbatch, chunk_frames,
                               compressed or shuffled, shuffled, (("key", name),)))
    specs += [ArraySpec("provenance/" + p, np.dtype(np.int64), (), nbatch) for p in PROVENANCE]
    return specs


def checksum_spec(specs: list[ArraySpec]) -> ArraySpec:
    """`provenance/checksum`: per batch slot, the (bytes, CRC-32) of each array's shard, in
    the order its attribute `arrays` names them (0, 0 for an array without values). Its
    attribute `metadata` keeps each array's `zarr.json` as written (`recorded`): a removed
    array or an edited dtype or shape is then named at open, and restored by a resumed
    write."""
    names = sorted(s.name for s in specs)
    metadata = {s.name: recorded(s.metadata(0)) for s in specs}
    return ArraySpec(CHECKSUM, np.dtype(np.uint64), (len(names), 2), 1,
                     attributes=(("arrays", names), ("metadata", metadata)))


def recorded(meta: Mapping[str, Any]) -> dict:
    """An array's metadata as the checksums' record keeps it: all of it but the number of
    trajectories, which grows with the store."""
    out = dict(meta)
    shape = out.get("shape")
    out["shape"] = [0, *shape[1:]] if isinstance(shape, list) and shape else shape
    return out


def largest_divisor(n: int, most: int) -> int:
    return max(d for d in range(1, min(n, most) + 1) if n % d == 0)


WRITTEN = ArraySpec("provenance/written", np.dtype(np.bool_), (), 1)
CHECKSUM = "provenance/checksum"

# --------------------------------------------------------------------------- files

class DamagedStore(ValueError):
    """A store's files disagree with its metadata or with themselves (truncated, emptied,
    missing, linked, or edited): the message names each file, its slot and what differs."""


def zstd():
    try:
        from numcodecs import Zstd
    except ImportError:
        raise ImportError("simloader.write: compressed arrays (images) need numcodecs: "
                          "pip install 'simloader[zarr]'") from None
    return Zstd(level=1)


def blosc():
    """The codec of shuffled arrays (`compression="zstd"`); its frames say their own type
    size, so one decoder reads them all."""
    try:
        from numcodecs import Blosc
    except ImportError:
        raise ImportError("simloader: compression='zstd' needs numcodecs: "
                          "pip install 'simloader[zarr]'") from None
    return Blosc(cname="zstd", clevel=1, shuffle=Blosc.SHUFFLE)


_POOL: Optional[tuple[int, Any]] = None
_POOL_LOCK = threading.Lock()


def _encoders():
    """Threads that compress chunks (zstd releases the GIL): camera images compress at about
    300 MB/s per core, a GPU renders them faster. One pool per process (a forked worker's
    copy of the parent's pool has no threads)."""
    global _POOL
    with _POOL_LOCK:  # the write pipeline's threads encode at once: one pool for them all
        if _POOL is None or _POOL[0] != os.getpid():
            from concurrent.futures import ThreadPoolExecutor
            _POOL = (os.getpid(), ThreadPoolExecutor(threads.available_cpus(),
                                                     thread_name_prefix="simloader-zstd"))
        return _POOL[1]


def encode_shard(spec: ArraySpec, rows: np.ndarray, clock: Any = None) -> tuple[list, int, int]:
    """One batch slot of one array in zarr's sharding format: the inner chunks in C order of
    the chunk grid (compressed over threads where the spec says so), then one (offset,
    length) pair of little-endian uint64 per chunk. Returns the parts to write, their size
    and their CRC-32. `clock` (`pipeline.Stages`) is told the seconds spent compressing and
    checksumming."""
    rows = np.ascontiguousarray(rows, dtype=spec.dtype.newbyteorder("<"))
    if spec.chunk_frames is None:
        chunks = [rows] if not spec.compressed else [rows[i] for i in range(len(rows))]
    else:  # camera frames: (trajectory, frame block) in C order
        f = spec.chunk_frames
        chunks = [rows[i, j:j + f] for i in range(len(rows)) for j in range(0, rows.shape[1], f)]
    start = time.perf_counter()
    if spec.compressed:
        codec = blosc() if spec.shuffled else zstd()
        parts = list(_encoders().map(lambda c: codec.encode(np.ascontiguousarray(c)), chunks))
        lengths = [len(p) for p in parts]
    else:  # raw: every trajectory's chunk is its rows, back to back
        parts = [memoryview(rows).cast("B")]
        size = rows[0].nbytes if len(rows) else 0
        lengths = [size] * len(rows) if spec.chunk_frames is None else [c.nbytes for c in chunks]
    encoded = time.perf_counter()
    offsets = np.concatenate([[0], np.cumsum(lengths[:-1])]).astype("<u8") if lengths else []
    index = np.stack([np.asarray(offsets, dtype="<u8"), np.asarray(lengths, dtype="<u8")],
                     axis=1)
    parts.append(index.tobytes())
    crc = 0
    for part in parts:  # zlib releases the GIL: other writer threads run meanwhile
        crc = zlib.crc32(part, crc)
    if clock is not None:
        clock.add("compress", encoded - start if spec.compressed else 0.0)
        clock.add("checksum", time.perf_counter() - encoded)
    return parts, sum(memoryview(p).nbytes for p in parts), crc


def crc_of(folder: Any, name: str, chunk: int = 1 << 22) -> int:
    """The CRC-32 of file `name` of a store's folder (`StoreFolder`), read in blocks."""
    crc = 0
    with os.fdopen(folder.open_file(name), "rb", buffering=0) as f:
        buffer = bytearray(chunk)
        view = memoryview(buffer)
        while True:
            n = f.readinto(buffer)
            if not n:
                return crc
            crc = zlib.crc32(view[:n], crc)
