"""The write pipeline: each batch slot's way from the simulator to a durable commit, its stages
overlapped so that the slowest one (the disk, the CPU or the simulator) sets the pace.

    simulate        the dataset's prefetch thread, `prefetch` batches ahead
    copy to host    a GPU batch's tensors into pinned host buffers, on a copy stream
                    (asynchronous: the next batch simulates meanwhile)
    per array, over threads:
      compress      zstd chunks (images; states with `compression="zstd"`)
      checksum      CRC-32 of the shard file's bytes
      write         the shard to a temporary file (NAME.<hex>.partial)
    sync            every temporary of the slot fsync'd at once (threads), renamed to its
                    name, the directories that name them fsync'd; then the checksums' shard,
                    durable, then the slot's mark, durable, last

A slot's commit keeps the order of the unpipelined writer (SQLite's and git's): its mark
(`provenance/written`) is written only after every shard of the slot and its checksums are on
the disk under their names. Slots commit independently of each other, in any order: a
reader takes committed slots only, and a resumed `write` redoes the rest.

Memory: at most `IN_FLIGHT` slots are between their copy and their commit. With the one being
simulated and the `prefetch` ones, a writer holds at most `prefetch + IN_FLIGHT + 1` batches
(GPU batches: `IN_FLIGHT` of them in pinned host memory, recycled from slot to slot).
"""

from __future__ import annotations

import collections
import dataclasses
import threading
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Optional

import numpy as np
import torch

from simloader import threads
from simloader.batch import flat
from simloader.store.folder import Staged, StoreFolder, folders_above
from simloader.store.zarr_format import (PROVENANCE, WRITTEN, ArraySpec, checksum_spec,
                                         encode_shard, store_path)

IN_FLIGHT = 2  # slots between their copy to the host and their commit, per writer


def shard_threads() -> int:
    """Threads that encode and write a slot's shards, per writer (the CPU stages')."""
    return min(8, threads.available_cpus())


STAGES = ("simulate", "copy to host", "compress", "checksum", "write", "sync")
_WAITED = "waited for the store"  # the writer blocked on a full pipeline


class Stages:
    """Seconds spent in each stage, summed over the threads that ran it (thread-safe)."""

    def __init__(self, seconds: Optional[Mapping[str, float]] = None):
        self.seconds: dict[str, float] = collections.defaultdict(float, seconds or {})
        self._lock = threading.Lock()

    def add(self, stage: str, seconds: float) -> None:
        with self._lock:
            self.seconds[stage] += seconds

    def take(self) -> dict[str, float]:
        """The seconds so far, and zero from now on (a worker sends them with a receipt)."""
        with self._lock:
            out, self.seconds = dict(self.seconds), collections.defaultdict(float)
        return out

    def merge(self, other: Mapping[str, float]) -> None:
        for stage, seconds in other.items():
            self.add(stage, seconds)

    def timed(self, stage: str) -> "_Timed":
        return _Timed(self, stage)


class _Timed:
    def __init__(self, stages: Stages, stage: str):
        self.stages, self.stage = stages, stage

    def __enter__(self) -> None:
        self.start = time.perf_counter()

    def __exit__(self, *exc: Any) -> None:
        self.stages.add(self.stage, time.perf_counter() - self.start)


@dataclasses.dataclass
class WriteReport:
    """What a `write` spent where: `seconds` of wall time for `batches` batches of `steps`
    steps in all, by `writers` writers (DataLoader workers or one process), and each stage's
    seconds summed over the writers and their threads (`STAGES`, and the time the writers
    waited for a full pipeline)."""

    batches: int
    steps: int
    seconds: float
    writers: int
    stages: dict[str, float]
    threads: int  # per writer, for the CPU stages

    @property
    def bound(self) -> str:
        """The part that set the pace. "the simulator" when the writers waited for batches
        more than for the store; otherwise the busiest of the store's stages, the disk
        (write + sync), the CPU (compress + checksum, over its threads) or the copy to the
        host."""
        s, wall = self.stages, max(self.seconds * self.writers, 1e-12)
        if s.get("simulate", 0.0) >= s.get(_WAITED, 0.0):
            return "the simulator"
        busy = {"the disk (write + sync)": (s.get("write", 0.0) + s.get("sync", 0.0)) / wall,
                "the CPU (compress + checksum)":
                    (s.get("compress", 0.0) + s.get("checksum", 0.0)) / (wall * self.threads),
                "the copy to the host": s.get("copy to host", 0.0) / wall}
        return max(busy, key=busy.__getitem__)

    def __str__(self) -> str:
        rate = self.steps / max(self.seconds, 1e-12)
        per = max(self.batches, 1)
        stages = ", ".join(f"{name} {self.stages.get(name, 0.0) / per:.3g}" for name in STAGES)
        wall = max(self.seconds * self.writers, 1e-12)
        return (f"{self.batches} batches, {self.steps:,} steps in {self.seconds:.1f} s "
                f"({rate / 1e6:.3g}M steps/s); seconds per batch: {stages}; waited for the "
                f"simulator {self.stages.get('simulate', 0.0) / wall:.0%} and for the store "
                f"{self.stages.get(_WAITED, 0.0) / wall:.0%} of the time: bound by "
                f"{self.bound}")


class _HostCopies:
    """A batch's tensors on the host: CPU tensors as they are (each batch's are its own, so
    holding them is safe), CUDA tensors copied into pinned buffers on a copy stream that
    waits for the producing stream; the buffers are recycled once their slot is committed."""

    def __init__(self) -> None:
        self.free: dict[tuple, list[torch.Tensor]] = collections.defaultdict(list)
        self.streams: dict[torch.device, Any] = {}
        self.lock = threading.Lock()

    def start(self, batch: Mapping[str, Any]) -> "_Copy":
        rows: dict[str, Any] = {}
        pinned: list[torch.Tensor] = []
        sources: list[torch.Tensor] = []
        events = []
        for name, value in flat(batch).items():
            if not isinstance(value, torch.Tensor) or not value.is_cuda:
                rows[name] = (value.detach().numpy() if isinstance(value, torch.Tensor)
                              else value)
                continue
            stream = self.streams.get(value.device)
            if stream is None:
                stream = self.streams[value.device] = torch.cuda.Stream(value.device)
            buffer = self._take(tuple(value.shape), value.dtype)
            stream.wait_stream(torch.cuda.current_stream(value.device))
            with torch.cuda.stream(stream):
                begin = torch.cuda.Event(enable_timing=True)
                end = torch.cuda.Event(enable_timing=True)
                begin.record(stream)
                buffer.copy_(value, non_blocking=True)
                end.record(stream)
            # the source must outlive the copy: record_stream tells torch's allocator, but
            # an engine's own memory (JAX's, Warp's, through DLPack) is held by reference
            value.record_stream(stream)
            sources.append(value)
            pinned.append(buffer)
            events.append((begin, end))
            rows[name] = buffer.numpy()
        return _Copy(self, rows, pinned, events, sources)

    def _take(self, shape: tuple, dtype: torch.dtype) -> torch.Tensor:
        with self.lock:
            free = self.free[(shape, dtype)]
            if free:
                return free.pop()
        return torch.empty(shape, dtype=dtype, pin_memory=True)

    def give_back(self, buffers: list[torch.Tensor]) -> None:
        with self.lock:
            for b in buffers:
                self.free[(tuple(b.shape), b.dtype)].append(b)


@dataclasses.dataclass
class _Copy:
    owner: _HostCopies
    rows: dict[str, Any]
    pinned: list[torch.Tensor]
    events: list
    sources: list  # the device tensors copied from, held until the copies are done

    def wait(self) -> float:
        """Waits for the copies; returns the seconds the copy engine spent on them."""
        seconds = 0.0
        for begin, end in self.events:
            end.synchronize()
            seconds += begin.elapsed_time(end) / 1e3
        self.sources = []
        return seconds

    def release(self) -> None:
        self.owner.give_back(self.pinned)
        self.pinned = []


class SlotPipeline:
    """Commits batch slots of one writer while the next batches simulate: `submit` starts a
    slot's copy to the host and hands its commit to a thread (blocking while `IN_FLIGHT` are
    pending), `completed` yields the receipts of the slots committed since, and `finish`
    waits for the rest. An error in a commit is raised by the next call; the slots
    committed before it stay committed."""

    def __init__(self, folder: StoreFolder, specs: dict[str, ArraySpec], nbatch: int,
                 stages: Stages):
        self.folder, self.specs, self.nbatch, self.stages = folder, specs, nbatch, stages
        self.checksums = checksum_spec(list(specs.values()))
        self.copies = _HostCopies()
        self.pending: collections.deque[Future] = collections.deque()
        self.slots = ThreadPoolExecutor(IN_FLIGHT, thread_name_prefix="simloader-commit")
        self.arrays = ThreadPoolExecutor(shard_threads(), thread_name_prefix="simloader-shard")

    def submit(self, slot: int, batch: Mapping[str, Any], where: tuple[int, int, int]) -> None:
        """Starts committing `batch` as `slot` (`where`: rank, batch index, workers)."""
        if len(self.pending) >= IN_FLIGHT:
            with self.stages.timed(_WAITED):
                self.pending[0].exception()  # waits; its receipt is taken by `completed`
        copy = self.copies.start(batch)
        self.pending.append(self.slots.submit(self._commit, slot, copy, where))

    def completed(self) -> Iterator[tuple[int, int, int]]:
        """(slot, trajectories, diverged) of each slot committed so far, in submission order
        (an error of a commit raises here)."""
        while self.pending and self.pending[0].done():
            yield self.pending.popleft().result()

    def finish(self) -> Iterator[tuple[int, int, int]]:
        """The receipts of the slots still pending, waiting for each."""
        while self.pending:
            with self.stages.timed(_WAITED):
                self.pending[0].exception()
            yield self.pending.popleft().result()

    def close(self) -> None:
        """Waits for the commits under way (each either commits or fails whole) and stops the
        threads; an error of theirs is not raised again (the caller is leaving already)."""
        for future in self.pending:
            future.exception()
        self.pending.clear()
        self.slots.shutdown(wait=True)
        self.arrays.shutdown(wait=True)

    def _commit(self, slot: int, copy: _Copy, where: tuple[int, int, int]) -> tuple:
        try:
            self.stages.add("copy to host", copy.wait())
            rows_of = self._rows(copy.rows, where)
            diverged = int(np.count_nonzero(rows_of["diverged"])) if "diverged" in rows_of \
                else 0
            commit_slot(self.folder, self.specs, self.checksums, slot, rows_of, self.stages,
                        self.arrays)
        finally:
            copy.release()
        return slot, self.nbatch, diverged

    def _rows(self, host: Mapping[str, Any], where: tuple[int, int, int]) -> dict[str, Any]:
        """Each stored array's rows of the batch: per-batch scalars (policy/version) one per
        trajectory, and the provenance of the slot."""
        rank, index, num_workers = where
        rows_of = {}
        for name, rows in host.items():
            spec = self.specs[store_path(name)]
            if spec.trailing == () and np.ndim(rows) == 0:
                rows = np.full(self.nbatch, rows, dtype=spec.dtype)
            rows_of[spec.name] = rows
        for p, value in zip(PROVENANCE, (rank, index, None, num_workers)):
            rows_of["provenance/" + p] = (np.arange(self.nbatch) if p == "row" else
                                          np.full(self.nbatch, value))
        return rows_of


def commit_slot(folder: StoreFolder, specs: Mapping[str, ArraySpec], checksums: ArraySpec,
                slot: int, rows_of: Mapping[str, Any], stages: Stages,
                pool: ThreadPoolExecutor) -> None:
    """Commits one batch slot: every shard written to a temporary file (in `pool`'s threads),
    all fsync'd, renamed to their names, and the directories that name them fsync'd; then the
    shards' sizes and checksums, durably; last the mark that the slot is complete. Every
    file is reached through the store's open folder, no link followed; a temporary is
    renamed in the folder it was written in."""
    names = dict(checksums.attributes)["arrays"]

    def stage(name: str) -> tuple[int, int, Optional[tuple[Staged, str, str]]]:
        spec = specs[name]
        if spec.empty:
            return 0, 0, None
        parts, size, crc = encode_shard(spec, rows_of[name], stages)
        file = spec.shard_key(slot)
        with stages.timed("write"):
            staged = folder.stage(file, parts)
        return size, crc, (staged, file, spec.name)

    staged = _all(pool, stage, names, lambda out: out[2] is not None and out[2][0].discard())
    files = [f for _, _, f in staged if f is not None]
    try:
        with stages.timed("sync"):
            _all(pool, lambda f: f[0].fsync(), files, lambda _: None)
        start = time.perf_counter()
        directories: set[str] = set()
        for temporary, file, array in files:
            temporary.commit()
            directories.update(folders_above(file, array))
    finally:
        for temporary, _, _ in files:
            temporary.discard()  # those not renamed (a failed fsync or rename)
    folder.sync(directories)  # the shards are on the disk under their names
    recorded = np.array([[[size, crc] for size, crc, _ in staged]], dtype=np.uint64)
    _, _, changed = write_shard(folder, checksums, slot, recorded)
    folder.sync(changed)
    _, _, changed = write_shard(folder, WRITTEN, slot, np.ones(1, dtype=bool))  # last
    folder.sync(changed)
    stages.add("sync", time.perf_counter() - start)


def write_shard(folder: Any, spec: ArraySpec, slot: int, rows: np.ndarray,
                durable: bool = True) -> tuple[int, int, list[str]]:
    """One batch slot of one array (`encode_shard`) written to its file at once (the
    checksums' and the marks' small shards; the write pipeline stages the others).

    `folder`: the store's `StoreFolder`. Returns the file's size, its CRC-32, and the folders
    to fsync before the slot is committed (`durable`: the file itself is fsync'd before its
    rename)."""
    if spec.empty:
        return 0, 0, []
    parts, size, crc = encode_shard(spec, rows)
    file = spec.shard_key(slot)
    folder.write(file, parts, durable)
    return size, crc, folders_above(file, spec.name)


def _all(pool: ThreadPoolExecutor, work: Any, items: list, undo: Any) -> list:
    """`work` over `items` in `pool`, every one run to its end; if any fails, `undo` is called
    on the results of those that did not, then the first error raised: no temporary file of
    a failed slot stays behind."""
    futures = [pool.submit(work, item) for item in items]
    errors = [f.exception() for f in futures]
    failed = next((e for e in errors if e is not None), None)
    if failed is None:
        return [f.result() for f in futures]
    for future, error in zip(futures, errors):
        if error is None:
            undo(future.result())
    raise failed
