"""Keeping the stream: `write` a dataset's batches into a zarr v3 store, `StoredDataset` to
read them back, and the regeneration of any stored trajectory from its provenance.

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

A shard is written by `_write_shard` in zarr's sharding format (inner chunks in C order,
then the index of (offset, length) pairs; no checksum), and read back by `StoredDataset` by
memory-mapping raw shards (a trajectory is a slice of the file) or decoding compressed chunks;
the tests read every store through zarr-python as well.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import json
import math
import os
import sys
import uuid
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any, Optional

import numpy as np
import torch

from simloader import resume, sharding

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
        return "/".join([self.name, "c", str(slot)] + ["0"] * len(self.trailing))


_ZARR_DTYPES = {"b1": "bool", "u1": "uint8", "i1": "int8", "i2": "int16", "i4": "int32",
                "i8": "int64", "u2": "uint16", "u4": "uint32", "u8": "uint64",
                "f2": "float16", "f4": "float32", "f8": "float64"}


def _leaves(batch: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(store name, tensor) of every tensor of a batch; `params` is a dict of tensors."""
    for key, value in batch.items():
        if isinstance(value, Mapping):
            yield from _leaves(value, prefix + key + "/")
        else:
            yield prefix + key, value


def _safe(name: str) -> str:
    """A batch key as a zarr path: its "/" are groups; other characters are kept except a
    leading "__" (reserved by zarr)."""
    return "/".join(("_" + p[2:] if p.startswith("__") else p) for p in name.split("/"))


def specs_of(batch: Mapping[str, Any], nbatch: int) -> list[ArraySpec]:
    """The stored arrays of a batch: every tensor key, `policy/version` (one per batch) made
    one per trajectory, and the provenance arrays."""
    specs = []
    for name, value in _leaves(batch):
        array = np.asarray(value.detach().cpu() if isinstance(value, torch.Tensor) else value)
        trailing = tuple(array.shape[1:]) if array.ndim and array.shape[0] == nbatch else ()
        dtype = np.dtype(array.dtype)
        chunk_frames = None
        if name.startswith("camera/") and len(trailing) >= 3:  # nframes x height x width ...
            frame_bytes = int(np.prod(trailing[1:])) * dtype.itemsize
            chunk_frames = _largest_divisor(trailing[0], max(1, _IMAGE_CHUNK_BYTES // frame_bytes))
        chunk_bytes = (int(np.prod(trailing)) * dtype.itemsize if chunk_frames is None else
                       chunk_frames * int(np.prod(trailing[1:])) * dtype.itemsize)
        compressed = dtype.kind in "biu" and chunk_bytes >= _COMPRESS_MIN_BYTES
        specs.append(ArraySpec(_safe(name), dtype, trailing, nbatch, chunk_frames, compressed))
    specs += [ArraySpec("provenance/" + p, np.dtype(np.int64), (), nbatch) for p in PROVENANCE]
    return specs


def _largest_divisor(n: int, most: int) -> int:
    return max(d for d in range(1, min(n, most) + 1) if n % d == 0)


WRITTEN = ArraySpec("provenance/written", np.dtype(np.bool_), (), 1)


# --------------------------------------------------------------------------- files

def _atomic_write(path: str, parts: Sequence[Any]) -> None:
    """Writes `parts` (bytes-like) to `path` through a temporary file renamed over it: a
    reader or a resumed writer sees the whole file or none of it."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    temporary = f"{path}.{uuid.uuid4().hex}.partial"
    try:
        with open(temporary, "wb") as f:
            for part in parts:
                f.write(part)
        os.replace(temporary, path)
    except BaseException:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise


def _write_json(path: str, value: dict) -> None:
    _atomic_write(path, [json.dumps(value, indent=2, sort_keys=True).encode()])


def _read_json(path: str) -> Optional[dict]:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        return None


def _zstd():
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


def _write_shard(root: str, spec: ArraySpec, slot: int, rows: np.ndarray) -> None:
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
        codec = _zstd()
        parts = list(_encoders().map(lambda c: codec.encode(np.ascontiguousarray(c)), chunks))
        lengths = [len(p) for p in parts]
    else:  # raw: every trajectory's chunk is its rows, back to back
        parts = [memoryview(rows).cast("B")]
        size = rows[0].nbytes if len(rows) else 0
        lengths = [size] * len(rows) if spec.chunk_frames is None else [c.nbytes for c in chunks]
    offsets = np.concatenate([[0], np.cumsum(lengths[:-1])]).astype("<u8") if lengths else []
    index = np.stack([np.asarray(offsets, dtype="<u8"), np.asarray(lengths, dtype="<u8")],
                     axis=1)
    _atomic_write(os.path.join(root, spec.shard_key(slot)), [*parts, index.tobytes()])


# --------------------------------------------------------------------------- provenance

def versions() -> dict[str, Optional[str]]:
    """The versions of the libraries a stored stream depends on (None: not installed)."""
    out = {}
    for name in ("simloader", "mujoco", "mujoco-mjx", "jax", "mujoco-warp", "warp-lang",
                 "torch", "numpy"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


# the versions whose change changes the simulated values (a stale store must not be resumed
# by another build of the simulator)
SIMULATING = ("simloader", "mujoco", "mujoco-mjx", "jax", "mujoco-warp", "warp-lang")


def fingerprint(dataset: Any) -> dict:
    """What must match to append to a store or regenerate from it: the resume fingerprint
    without `num_batches` (the store's size is `batches`)."""
    out = dict(resume.fingerprint(dataset.config))
    out.pop("num_batches")
    return out


def _differences(stored: dict, mine: dict) -> list[str]:
    return [f"{k}: stored {stored.get(k)!r}, given {mine.get(k)!r}"
            for k in sorted(set(stored) | set(mine)) if stored.get(k) != mine.get(k)]


def provenance(dataset: Any, batches: int) -> dict:
    """The store's root attribute: what made it, and how to make it again."""
    c = dataset.config
    return {"format": FORMAT, "fingerprint": fingerprint(dataset),
            "describe": dataset.describe(), "seed": c.seed, "nbatch": c.nbatch,
            "nstep": c.nstep, "record_every": c.record_every, "batches": batches,
            "versions": versions()}


class StoreMismatch(ValueError):
    """An existing store holds another configuration (or simulator build) than the dataset."""


def _open_for_writing(path: str, dataset: Any, batches: int) -> dict:
    """Creates the store's root, or checks that an existing one holds this configuration, and
    grows its size to `batches` slots. Every writer does the same, with the same result."""
    mine = provenance(dataset, batches)
    root = _read_json(os.path.join(path, "zarr.json"))
    if root is not None:
        stored = root.get("attributes", {}).get(ATTRIBUTE)
        if stored is None or stored.get("format") != FORMAT:
            raise StoreMismatch(f"path: {path!r} is not a simloader store of format {FORMAT} "
                                f"(its root has no {ATTRIBUTE!r} attribute of that format)")
        differ = _differences(stored["fingerprint"], mine["fingerprint"])
        if differ:
            raise StoreMismatch(f"path: the store at {path!r} holds another configuration; "
                                f"it cannot be appended to ({'; '.join(differ)})")
        stale = [f"{k} {stored['versions'].get(k)} (now {mine['versions'].get(k)})"
                 for k in SIMULATING if stored["versions"].get(k) != mine["versions"].get(k)]
        if stale:
            raise StoreMismatch(f"path: the store at {path!r} was simulated by other versions "
                                f"({', '.join(stale)}); its trajectories would not continue "
                                f"the same stream; write to a new path")
        mine["batches"] = max(batches, stored["batches"])
        mine["describe"] = stored["describe"]
    if root is None or mine["batches"] != root["attributes"][ATTRIBUTE]["batches"]:
        _write_json(os.path.join(path, "zarr.json"), {
            "zarr_format": 3, "node_type": "group", "attributes": {ATTRIBUTE: mine}})
        _ensure_array(path, WRITTEN, mine["batches"])
    return mine


def _ensure_array(path: str, spec: ArraySpec, ntrajectories: int) -> None:
    """Writes the array's metadata (and its groups'), or grows it; refuses another shape or
    dtype under the same name."""
    parts = spec.name.split("/")
    for depth in range(1, len(parts)):
        group = os.path.join(path, *parts[:depth], "zarr.json")
        if not os.path.exists(group):
            _write_json(group, {"zarr_format": 3, "node_type": "group", "attributes": {}})
    where = os.path.join(path, spec.name, "zarr.json")
    wanted = spec.metadata(ntrajectories)
    existing = _read_json(where)
    if existing is not None:
        if {**existing, "shape": None} != {**wanted, "shape": None}:
            raise StoreMismatch(f"path: the store's array {spec.name!r} has shape "
                                f"{existing['shape']} and dtype {existing['data_type']}; "
                                f"this dataset's batches give {wanted['shape']} and "
                                f"{wanted['data_type']}")
        if existing["shape"][0] >= ntrajectories:
            return
    _write_json(where, wanted)


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


# --------------------------------------------------------------------------- writing

def slots_of(rank: int, world: int, batches: int) -> int:
    """How many batch indices rank `rank` of `world` writes: those with `i * world + rank <
    batches`."""
    return max(0, math.ceil((batches - rank) / world))


class _Writer(torch.utils.data.IterableDataset):
    """Simulates this worker's missing slots and writes each, yielding a receipt per batch
    (slot, trajectories, diverged): the batches themselves never cross the worker's queue."""

    def __init__(self, dataset: Any, path: str, batches: int, rank: tuple[int, int]):
        self.dataset, self.path, self.batches, self.rank = dataset, path, batches, rank

    def __iter__(self) -> Iterator[tuple[int, int, int]]:
        ds = self.dataset
        shard = sharding.current_shard(self.rank)
        done = written_slots(self.path, self.batches)
        count = slots_of(shard.rank, shard.world_size, self.batches)
        mine = list(shard.indices(count))
        # a continued episode needs every batch before it: simulate them, write the missing
        todo = mine if ds.config.continue_episodes else [
            i for i in mine if not done[i * shard.world_size + shard.rank]]
        if not todo:
            return
        specs: Optional[dict[str, ArraySpec]] = None
        backend = ds.make_backend(shard)
        for index, batch, _ in ds.stream(backend, todo):
            slot = index * shard.world_size + shard.rank
            if done[slot]:
                continue
            if specs is None:
                specs = {s.name: s for s in specs_of(batch, ds.config.nbatch)}
                for spec in specs.values():
                    _ensure_array(self.path, spec, self.batches * ds.config.nbatch)
            _write_slot(self.path, specs, slot, batch, ds.config.nbatch,
                        (shard.rank, index, shard.num_workers))
            yield slot, ds.config.nbatch, int(batch["diverged"].sum())


def _write_slot(path: str, specs: dict[str, ArraySpec], slot: int, batch: Mapping[str, Any],
                nbatch: int, where: tuple[int, int, int]) -> None:
    rank, index, num_workers = where
    for name, value in _leaves(batch):
        spec = specs[_safe(name)]
        rows = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
        if spec.trailing == () and np.ndim(rows) == 0:  # one per batch: one per trajectory
            rows = np.full(nbatch, rows, dtype=spec.dtype)
        _write_shard(path, spec, slot, rows)
    for p, value in zip(PROVENANCE, (rank, index, None, num_workers)):
        rows = np.arange(nbatch) if p == "row" else np.full(nbatch, value)
        _write_shard(path, specs["provenance/" + p], slot, rows)
    _write_shard(path, WRITTEN, slot, np.ones(1, dtype=bool))  # last: the slot is complete


def write(dataset: Any, path: str | os.PathLike, *, batches: int, format: str = "zarr",
          num_workers: int = 0, progress: bool = True) -> str:
    """Streams `batches` batches of `dataset` into a store at `path` and returns the path.

    `format="zarr"`: a zarr v3 group (see this module's docstring for the layout); every batch
    key becomes an array `batches * nbatch x ...` in its own dtype. `batches` counts all
    ranks' batches: under torchrun each rank calls `write` with the same arguments and
    writes its own slots. `num_workers > 0` simulates and writes in DataLoader workers, each
    its own slots. At most `prefetch + 1` batches per worker are in memory.

    An existing store of the same configuration is resumed: slots already complete are
    skipped (a killed writer loses the batch in flight only), and a larger `batches` appends.
    One of another configuration or simulator version is refused, naming what differs.

    `format="minari"`: a Minari dataset (see `simloader.store_minari`), named after the last
    component of `path`, under its parent directory.

    Raises:
      ValueError: bad arguments; a store of another configuration at `path`.
      OSError: the disk is full or not writable (the store stays readable, holding the
        batches completed so far; writing again resumes).
    """
    if not isinstance(batches, int) or isinstance(batches, bool) or batches < 1:
        raise ValueError(f"batches: expected a positive int, got {batches!r}")
    if not isinstance(num_workers, int) or num_workers < 0:
        raise ValueError(f"num_workers: expected an int >= 0, got {num_workers!r}")
    path = os.fspath(path)
    if format == "minari":
        from simloader import store_minari
        return store_minari.write(dataset, path, batches=batches, progress=progress,
                                  metadata=provenance(dataset, batches))
    if format != "zarr":
        raise ValueError(f"format: expected 'zarr' or 'minari', got {format!r}")
    rank = sharding.distributed_rank() or (0, 1)
    try:
        info = _open_for_writing(path, dataset, batches)
        batches = info["batches"]
        total = slots_of(rank[0], rank[1], batches)
        done = written_slots(path, batches)
        already = int(sum(done[i * rank[1] + rank[0]] for i in range(total)))
        loader = torch.utils.data.DataLoader(
            _Writer(dataset, path, batches, rank), batch_size=None, num_workers=num_workers,
            multiprocessing_context=_worker_start(dataset) if num_workers else None)
        bar = _progress(progress, total, already, path)
        try:
            for _, _, diverged in loader:
                bar.update(1)
                if diverged:
                    bar.set_postfix(diverged=diverged, refresh=False)
        finally:
            bar.close()
    except OSError as e:
        raise OSError(e.errno, f"write: {e.strerror or e} while writing the store at "
                               f"{path!r}; it stays readable with the batches completed so "
                               f"far, and calling write again resumes after them",
                      e.filename) from e
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.barrier()  # the store is complete when every rank's part is
    return path


def _worker_start(dataset: Any) -> Optional[str]:
    """How `write` starts its workers: fork unless the dataset renders (OpenGL's state does
    not survive a fork) or runs on a GPU (CUDA's does not either), then spawn."""
    c = dataset.config
    renders = any(o.rendered for o in c.observations)
    gpu = c.backend != "rollout" or (c.device is not None and torch.device(c.device).type != "cpu")
    return "spawn" if renders or gpu else None


def _progress(enabled: bool, total: int, already: int, path: str):
    from tqdm import tqdm
    return tqdm(total=total, initial=already, unit="batch", desc=f"write {path}",
                disable=not enabled, file=sys.stderr, leave=False)


# --------------------------------------------------------------------------- reading

class _Shard:
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
        codec = _zstd() if self.compressed else None
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


class _Array:
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
        self._shards: dict[int, _Shard] = {}

    def _shard(self, slot: int) -> _Shard:
        shard = self._shards.get(slot)
        if shard is None:
            key = "/".join([self.name, "c", str(slot)] + ["0"] * len(self.trailing))
            shard = self._shards[slot] = _Shard(os.path.join(self.root, key),
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


def _arrays(path: str) -> dict[str, dict]:
    """Every array of the store below its root: {name: zarr metadata}."""
    out = {}
    for directory, subdirs, files in os.walk(path):
        subdirs[:] = [d for d in subdirs if d != "c"]  # chunk folders hold no metadata
        if "zarr.json" in files and directory != path:
            meta = _read_json(os.path.join(directory, "zarr.json"))
            if meta.get("node_type") == "array":
                out[os.path.relpath(directory, path).replace(os.sep, "/")] = meta
    return out


def _nest(flat: Mapping[str, torch.Tensor]) -> dict[str, Any]:
    """`params/KEY` back into `{"params": {KEY: ...}}`, as the batch held them."""
    out: dict[str, Any] = {}
    for name, value in flat.items():
        if name.startswith("params/"):
            out.setdefault("params", {})[name[len("params/"):]] = value
        else:
            out[name] = value
    return out


class StoredDataset(torch.utils.data.Dataset):
    """A map-style dataset over a store that `simloader.write` made: item `i` is stored
    trajectory `i`, a dict of tensors keyed as the batch was (`params` a dict of them),
    without the leading `nbatch`.

    Only complete batch slots are seen, so a store still being written (or whose writer was
    killed) is readable. Reading memory-maps the shards: a trajectory's float arrays are
    slices of the files, copied once into the item's tensors; images are decoded per block of
    frames. Safe in DataLoader workers (files are opened in each process).

    Args:
      path: the store.
      keys: the batch keys to read (default: all but `provenance/`); `"params"` stands for
        all of `params/`.
    """

    def __init__(self, path: str | os.PathLike, keys: Optional[Sequence[str]] = None):
        self.path = os.fspath(path)
        root = _read_json(os.path.join(self.path, "zarr.json"))
        if root is None or ATTRIBUTE not in root.get("attributes", {}):
            raise ValueError(f"path: {self.path!r} is not a simloader store (no zarr.json "
                             f"with a {ATTRIBUTE!r} attribute)")
        self.info = root["attributes"][ATTRIBUTE]
        if self.info.get("format") != FORMAT:
            raise ValueError(f"path: store format {self.info.get('format')}, this simloader "
                             f"reads format {FORMAT}")
        metas = _arrays(self.path)
        available = [n for n in metas if not n.startswith("provenance/")]
        if keys is None:
            names = available
        else:
            names = []
            for key in keys:
                found = [n for n in available if n == key or n.startswith(key + "/")]
                if not found:
                    from simloader.layout import did_you_mean
                    raise KeyError(f"keys: the store has no key {key!r}"
                                   f"{did_you_mean(key, available)}; it has {sorted(available)}")
                names += found
        self.keys = sorted(set(names))
        self.nbatch = int(self.info["nbatch"])
        slots = np.flatnonzero(written_slots(self.path, int(self.info["batches"])))
        self.slots = slots  # complete batch slots, in order
        self._metas = {n: metas[n] for n in self.keys + [p for p in metas
                                                         if p.startswith("provenance/")]}
        self._open: Optional[tuple[int, dict[str, _Array]]] = None

    def __len__(self) -> int:
        return len(self.slots) * self.nbatch

    def _arrays(self) -> dict[str, _Array]:
        # opened per process: memory maps and file handles do not cross a fork cleanly
        if self._open is None or self._open[0] != os.getpid():
            self._open = (os.getpid(), {n: _Array(self.path, n, m)
                                        for n, m in self._metas.items()})
        return self._open[1]

    def locate(self, i: int) -> tuple[int, int]:
        """(batch slot, row) of stored trajectory `i`."""
        if not -len(self) <= i < len(self):
            raise IndexError(f"StoredDataset: index {i} out of range for {len(self)} "
                             f"trajectories")
        i %= len(self)
        return int(self.slots[i // self.nbatch]), i % self.nbatch

    def read(self, i: int, names: Iterable[str]) -> dict[str, np.ndarray]:
        slot, row = self.locate(i)
        arrays = self._arrays()
        return {n: arrays[n].trajectory(slot, row) for n in names}

    def __getitem__(self, i: int) -> dict[str, Any]:
        return _nest({n: torch.from_numpy(np.array(a)) for n, a in self.read(i, self.keys).items()})

    def provenance(self, i: int) -> dict[str, int]:
        """Where stored trajectory `i` comes from in the seeded stream: rank, batch (the
        rank's batch index), row, and the DataLoader workers that wrote it."""
        return {p: int(v) for p, v in self.read(i, ["provenance/" + p for p in PROVENANCE]
                                                ).items() for p in [p.split("/")[1]]}

    def transitions(self, state: str | Sequence[str] = "state",
                    diverged: str = "drop") -> "Transitions":
        """The stored trajectories as transitions `(s_t, a_t, s_t+1)` (see `Transitions`);
        `diverged="drop"` leaves out the trajectories flagged `diverged` (or `overflow`):
        what follows an instability is not physics to learn. `"keep"` keeps them."""
        if diverged not in ("drop", "keep"):
            raise ValueError(f"diverged: expected 'drop' or 'keep', got {diverged!r}")
        return Transitions(self, (state,) if isinstance(state, str) else tuple(state),
                           drop_flagged=diverged == "drop")

    def flagged(self) -> np.ndarray:
        """Per stored trajectory: flagged `diverged` or `overflow` (bool)."""
        arrays = {n: _Array(self.path, n, m) for n, m in _arrays(self.path).items()
                  if n in ("diverged", "overflow")}
        out = np.zeros(len(self), dtype=bool)
        for k, slot in enumerate(self.slots):
            for array in arrays.values():
                out[k * self.nbatch:(k + 1) * self.nbatch] |= array.slot(int(slot))
        return out

    def regenerate(self, dataset: Any, i: int) -> dict[str, Any]:
        """Simulates stored trajectory `i` again from its provenance and returns it as item
        `i` is returned. `dataset` is built with the same arguments as the writer's (its
        `num_batches` aside); on the CPU backend the result equals the stored trajectory bit
        for bit, on the GPU within the named tolerances. A continued episode replays its
        worker's batches before it.

        Raises:
          ValueError: another configuration (naming what differs), or a `policy=` stream
            (its weights changed while it was written and are not stored).
        """
        differ = _differences(self.info["fingerprint"], fingerprint(dataset))
        if differ:
            raise ValueError(f"dataset: not the configuration that wrote {self.path!r} "
                             f"({'; '.join(differ)})")
        if dataset.config.policy is not None:
            raise ValueError("dataset: a policy= stream cannot be regenerated (its weights "
                             "changed while it was written and are not in the store)")
        where = self.provenance(i)
        rank, index, workers = where["rank"], where["batch"], where["num_workers"]
        if dataset.config.continue_episodes:
            indices = list(range(index % workers, index + 1, workers))
        else:
            indices, workers = [index], 1
        shard = sharding.Shard(rank=rank, world_size=rank + 1, worker=index % workers,
                               num_workers=workers)
        batch = None
        for _, batch, _ in dataset.stream(dataset.make_backend(shard), indices):
            pass
        flat = dict(_leaves(batch))
        row = where["row"]
        out = {}
        for name in self.keys:
            value = flat[name]
            out[name] = value[row] if value.ndim and value.shape[0] == self.nbatch \
                else value.expand(self.nbatch)[row]
        return _nest({n: v.detach().cpu().clone() for n, v in out.items()})


class Transitions(torch.utils.data.Dataset):
    """The transitions of a store: item `k` is `{KEY: s_t, "control": a_t, "next/KEY": s_t+1}`
    for every state key, over the trajectories not flagged diverged (by default). With `record_every = k` the action is the `k` control rows between
    two frames (`k x ncontrol`). The first frame's predecessor is the initial state for the
    key `"state"` (`initial_state`), so a trajectory gives `nframes` transitions; other keys
    have no stored initial value and give `nframes - 1`.
    """

    def __init__(self, stored: StoredDataset, keys: tuple[str, ...], drop_flagged: bool):
        metas = _arrays(stored.path)
        for key in keys:
            if key not in metas or len(metas[key]["shape"]) < 2:
                raise KeyError(f"state: expected a per-frame key of the store, got {key!r}; "
                               f"per-frame keys: {sorted(n for n, m in metas.items() if len(m['shape']) >= 2 and not n.startswith('provenance/'))}")
        self.stored = StoredDataset(stored.path, keys=list(keys) + ["control"] + (
            ["initial_state"] if "state" in keys else []))
        self.keys = keys
        self.every = int(stored.info["record_every"])
        self.nframes = int(metas[keys[0]]["shape"][1])
        self.first = 0 if keys == ("state",) else 1  # frame 0's predecessor is stored
        self.per = self.nframes - self.first
        # the stored trajectories whose transitions these are
        self.trajectories = (np.flatnonzero(~stored.flagged()) if drop_flagged else
                             np.arange(len(stored)))

    def __len__(self) -> int:
        return len(self.trajectories) * self.per

    def __getitem__(self, k: int | Sequence[int]) -> dict[str, torch.Tensor]:
        """Transition `k`, or for a sequence of indices the batch of them (what `loader`'s
        batch sampler asks for: no per-item tensors, no collation)."""
        if isinstance(k, (int, np.integer)):
            return {n: v[0] for n, v in self.gather([k]).items()}
        return self.gather(k)

    def __getitems__(self, ks: Sequence[int]) -> list[dict[str, torch.Tensor]]:
        """A DataLoader's batch (`batch_size=B`): the items as views of one gather, which
        the default collation stacks again. `loader()` skips both."""
        out = self.gather(ks)
        return [dict(zip(out, values)) for values in zip(*(v.unbind(0) for v in out.values()))]

    def loader(self, batch_size: int, shuffle: bool = True, drop_last: bool = False,
               **kwargs: Any) -> torch.utils.data.DataLoader:
        """A DataLoader of batches of `batch_size` transitions, each read with one gather
        per key and batch slot: a batch sampler hands the dataset all of a batch's indices
        (`batch_size=None`), so no per-item tensors are made or collated. `kwargs` go to the
        DataLoader (`num_workers=`, ...)."""
        order = (torch.utils.data.RandomSampler(self) if shuffle else
                 torch.utils.data.SequentialSampler(self))
        return torch.utils.data.DataLoader(
            self, batch_size=None,
            sampler=torch.utils.data.BatchSampler(order, batch_size, drop_last), **kwargs)

    def gather(self, ks: Sequence[int]) -> dict[str, torch.Tensor]:
        """The transitions `ks` as a dict of tensors `len(ks) x ...`: one gather per key and
        batch slot, from the memory-mapped shards."""
        ks = np.asarray(ks, dtype=np.int64) % len(self)
        trajectories, frames = np.divmod(ks, self.per)
        trajectories = self.trajectories[trajectories]
        frames += self.first
        nbatch = self.stored.nbatch
        slots = self.stored.slots[trajectories // nbatch]
        rows = trajectories % nbatch
        arrays = self.stored._arrays()
        columns: dict[str, np.ndarray] = {}
        steps = np.arange(self.every)
        for slot in np.unique(slots):
            sel = np.flatnonzero(slots == slot)
            r, f = rows[sel], frames[sel]
            gathered = {}
            for key in self.keys:
                seq = arrays[key].slot(int(slot))
                gathered["next/" + key] = seq[r, f]
                before = seq[r, np.maximum(f - 1, 0)]
                if key == "state" and (f == 0).any():
                    first = f == 0
                    before[first] = arrays["initial_state"].slot(int(slot))[r[first]]
                gathered[key] = before
            control = arrays["control"].slot(int(slot))[r[:, None],
                                                         f[:, None] * self.every + steps]
            gathered["control"] = control[:, 0] if self.every == 1 else control
            for name, values in gathered.items():
                if name not in columns:
                    columns[name] = np.empty((len(ks), *values.shape[1:]), values.dtype)
                columns[name][sel] = values
        order = [*self.keys, "control", *("next/" + k for k in self.keys)]
        return {n: torch.from_numpy(columns[n]) for n in order}
