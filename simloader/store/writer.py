"""`write(format="zarr")`: a dataset's batches into a zarr store, by workers and ranks that
never coordinate (`simloader.store.front.write` checks the arguments and calls `write_zarr`)."""

from __future__ import annotations

import math
import os
import re
import sys
import time
from collections.abc import Iterator
from typing import Any, Optional

import numpy as np
import torch

from simloader import sharding
from simloader.store import integrity, lock, ownership, pipeline, pixels
from simloader.store.folder import StoreFolder, folders_above
from simloader.store.zarr_format import (ATTRIBUTE, CHECKSUM, FORMAT, WRITTEN, ArraySpec,
                                         checksum_spec, specs_of, zstd, blosc)
from simloader.store.provenance import (SIMULATING, StoreMismatch, differences, new_identity,
                                        provenance)


def _open_for_writing(folder: StoreFolder, dataset: Any, batches: int, ranks: int,
                      workers: int, create: bool, identity: Optional[str] = None) -> dict:
    """Creates the store's root, or checks that an existing one holds this configuration and
    was written by as many ranks (and, for continued episodes, DataLoader workers), and grows
    its size to `batches` slots. Only the lock's holder (`create`) writes; the other ranks of
    its job check what it wrote. A new store draws its identity (`provenance.new_identity`),
    which it keeps while it grows: a reader opened before a replace knows it was replaced."""
    path = folder.path
    mine = {**provenance(dataset, batches), "ranks": ranks, "id": identity or new_identity()}
    continued = bool(dataset.config.continue_episodes)
    if continued:
        mine["workers"] = workers
    root = folder.read_json("zarr.json")
    if root is not None:
        stored = (root.get("attributes") or {}).get(ATTRIBUTE) if isinstance(root, dict) \
            else None
        if not isinstance(stored, dict) or stored.get("format") != FORMAT:
            raise StoreMismatch(f"{path!r} is not a simloader store of format {FORMAT} "
                                f"(its root has no {ATTRIBUTE!r} attribute of that format)")
        if stored.get(ownership.REPLACING):
            raise StoreMismatch(ownership.replacing(path))
        missing = [k for k in ("fingerprint", "versions", "batches", "describe")
                   if k not in stored]
        if missing:
            raise StoreMismatch(f"the store at {path!r} lacks {missing} in its root's "
                                f"{ATTRIBUTE!r} attribute ({os.path.join(path, 'zarr.json')} "
                                f"was edited or damaged); write to a new path")
        differ = differences(stored["fingerprint"], mine["fingerprint"])
        if differ:
            raise StoreMismatch(f"the store at {path!r} holds another configuration; "
                                f"it cannot be appended to ({'; '.join(differ)})")
        stale = [f"{k} {stored['versions'].get(k)} (now {mine['versions'].get(k)})"
                 for k in SIMULATING if stored["versions"].get(k) != mine["versions"].get(k)]
        if stale:
            raise StoreMismatch(f"the store at {path!r} was simulated by other versions "
                                f"({', '.join(stale)}); its trajectories would not continue "
                                f"the same stream; write to a new path")
        if stored.get("ranks") != ranks:
            # slot i * ranks + rank: another number of ranks would put batches the store
            # holds already into other slots (a trajectory twice, another never)
            raise StoreMismatch(f"the store at {path!r} is written by "
                                f"{stored.get('ranks')} rank(s) (torchrun processes); resume "
                                f"or extend it with {stored.get('ranks')}, not {ranks}, or "
                                f"write to a new path")
        if continued and stored.get("workers", workers) != workers:
            # a continued episode chains a worker's batches: worker w of W continues batch
            # i - W in batch i, so other workers would continue other trajectories
            was = stored.get("workers")
            raise StoreMismatch(f"the store at {path!r} holds continued episodes "
                                f"(continue_episodes=True) written by {was} DataLoader "
                                f"worker(s); each worker's batches continue its own earlier "
                                f"ones, so resume or extend it with num_workers="
                                f"{'0 or 1' if was == 1 else was}, not {workers} worker(s), "
                                f"or write to a new path")
        mine["batches"] = max(batches, stored["batches"])
        mine["describe"] = stored["describe"]
        if "id" in stored:
            mine["id"] = stored["id"]
        else:  # written before stores had one: stays without
            mine.pop("id")
        if "models" not in stored:  # written before the models were kept: stays so
            mine.pop("models")
    if create and (root is None or mine["batches"] != stored["batches"]):
        # the models (once, when the store is made), and the slots' array, before the root:
        # a root never names models or more slots than the store holds
        if root is None:
            pixels.save_models(folder, pixels.pool_of(dataset.config)[1])
        _ensure_array(folder, WRITTEN, mine["batches"])
        folder.write_json("zarr.json", {
            "zarr_format": 3, "node_type": "group", "attributes": {ATTRIBUTE: mine}},
            durable=True)
        folder.sync([""])
    elif not create and (root is None or stored["batches"] < batches):
        raise StoreMismatch(f"rank 0 did not create the store at {path!r} for "
                            f"{batches} batches")
    return mine


def _ensure_groups(folder: StoreFolder, name: str) -> None:
    """The group `zarr.json`s above array `name`, durably."""
    parts = name.split("/")
    for depth in range(1, len(parts)):
        group = "/".join(parts[:depth] + ["zarr.json"])
        if folder.kind(group) is None:
            folder.write_json(group, {"zarr_format": 3, "node_type": "group",
                                      "attributes": {}}, durable=True)


def _ensure_array(folder: StoreFolder, spec: ArraySpec, ntrajectories: int) -> None:
    """Writes the array's metadata (and its groups'), durably, or grows it; refuses another
    shape or dtype under the same name."""
    _ensure_groups(folder, spec.name)
    name = spec.name + "/zarr.json"
    where = folder.where(name)
    wanted = spec.metadata(ntrajectories)
    existing = folder.read_json(name)
    if existing is not None:
        # attributes aside (stores written before the `key` attribute existed are extended
        # too), but not the checksums' list of arrays (nor their metadata's record, where
        # the store keeps one)
        ignored = {"shape": None, "attributes": None}
        kept = existing.get("attributes") or {}
        compared = () if spec.name != CHECKSUM else \
            ("arrays", "metadata") if "metadata" in kept else ("arrays",)
        same = all(kept.get(k) == wanted["attributes"][k] for k in compared)
        if not same or {**existing, **ignored} != {**wanted, **ignored}:
            raise StoreMismatch(
                f"the store's array {spec.name!r} ({where}) has shape "
                f"{existing.get('shape')}, dtype {existing.get('data_type')}, codecs "
                f"{_codecs(existing)} and attributes {existing.get('attributes')}; this "
                f"dataset's batches give {wanted['shape']}, {wanted['data_type']}, "
                f"{_codecs(wanted)} and {wanted['attributes']} (a store keeps the "
                f"compression= it was written with)")
        if existing["shape"][0] >= ntrajectories:
            return
    folder.write_json(name, wanted, durable=True)
    folder.sync(folders_above(name))


def _codecs(meta: dict) -> list:
    """The names of an array's codecs inside its shards (bytes, then zstd or blosc)."""
    try:
        return [c.get("name") for c in meta["codecs"][0]["configuration"]["codecs"]]
    except (KeyError, IndexError, TypeError, AttributeError):
        return [meta.get("codecs")]


def slots_of(rank: int, world: int, batches: int) -> int:
    """How many batch indices rank `rank` of `world` writes: those with `i * world + rank <
    batches`."""
    return max(0, math.ceil((batches - rank) / world))


class _Writer(torch.utils.data.IterableDataset):
    """Simulates this worker's missing slots and commits each through the write pipeline,
    yielding a receipt per slot (slot, trajectories, diverged, the seconds each stage took
    since the last receipt): the batches themselves never cross the worker's queue."""

    def __init__(self, dataset: Any, folder: StoreFolder, batches: int, rank: tuple[int, int],
                 done: np.ndarray, compression: Optional[str]):
        """`done`: the slots complete when `write` began (each slot has one writer, so no
        other writer completes one of this worker's meanwhile)."""
        self.dataset, self.folder, self.batches, self.rank = dataset, folder, batches, rank
        self.done, self.compression = done, compression

    def __iter__(self) -> Iterator[tuple[int, int, int, dict]]:
        ds, done = self.dataset, self.done
        shard = sharding.current_shard(self.rank)
        count = slots_of(shard.rank, shard.world_size, self.batches)
        mine = list(shard.indices(count))
        # a continued episode needs every batch before it: simulate them, write the missing
        todo = mine if ds.config.continue_episodes else [
            i for i in mine if not done[i * shard.world_size + shard.rank]]
        if not todo:
            return
        stages = pipeline.Stages()
        slots: Optional[pipeline.SlotPipeline] = None
        batches = ds.batches_at(todo, shard)
        try:
            while True:
                with stages.timed("simulate"):
                    got = next(batches, None)
                if got is None:
                    break
                index, batch = got
                slot = index * shard.world_size + shard.rank
                if done[slot]:
                    continue
                if slots is None:
                    specs = {s.name: s for s in specs_of(batch, ds.config.nbatch,
                                                         self.compression)}
                    for spec in specs.values():
                        _ensure_array(self.folder, spec, self.batches * ds.config.nbatch)
                    _ensure_array(self.folder, checksum_spec(list(specs.values())),
                                  self.batches)
                    slots = pipeline.SlotPipeline(self.folder, specs, ds.config.nbatch, stages)
                slots.submit(slot, batch, (shard.rank, index, shard.num_workers))
                del batch, got  # the pipeline holds it while it needs it
                for receipt in slots.completed():
                    yield (*receipt, stages.take())
            if slots is not None:
                for receipt in slots.finish():
                    yield (*receipt, stages.take())
        finally:
            batches.close()
            if slots is not None:
                slots.close()


class Written(str):
    """The path of a written store, with what the write spent where (`report`, a
    `pipeline.WriteReport`: the seconds of each stage and which one bounded the run)."""

    report: pipeline.WriteReport


def write_zarr(dataset: Any, path: str, *, batches: int, num_workers: int, progress: bool,
               replace: bool, compression: Optional[str] = None,
               member_of: Optional[StoreFolder] = None,
               identity: Optional[str] = None) -> Written:
    """`write(format="zarr")`, its arguments checked.

    Nothing is opened for writing before the path is known to be the store's to write
    (`ownership.check_path` and `check_contents`: a new or empty folder, a store, a killed
    creation; not inside another store) and the store holds no link; `replace=True` then
    removes the store's own entries only. Every file operation after the first check goes
    through the store's open folder (`simloader.store.folder`): a link swapped in meanwhile
    is refused, never followed. `member_of`: the mixture store's folder this member's store
    is written in (`path` is then relative to it); `identity`: the new store's identity (the
    one the mixture's root recorded for it)."""
    if any(o.rendered for o in dataset.config.observations):
        zstd()  # images are compressed: refuse now, naming the extra, not at the first batch
    if compression == "zstd":
        blosc()  # the same for compressed states
    rank = _writer_rank()
    job = _job_id(rank)
    workers = max(1, num_workers)
    folder: Optional[StoreFolder] = None
    held: Optional[lock.WriterLock] = None
    stage = "opening"  # what a failure leaves: `ownership.os_error_message`
    try:
        if rank[0] == 0:
            try:
                if member_of is not None:
                    folder = member_of.sub(path, create=True)
                    path = folder.path
                else:
                    ownership.check_path(path)  # reads only
                    folder = StoreFolder(path, create=True)
                ownership.check_contents(folder, replace)  # reads only
                held = lock.WriterLock(folder, job).acquire()
                found = integrity.survey(folder)
                if found.links:
                    ownership.refuse_links(folder, found.links)
                if replace:
                    stage = "replacing"
                    ownership.clear(folder)
                info = _open_for_writing(folder, dataset, batches, rank[1], workers,
                                         create=True, identity=identity)
                stage = "writing"
                _restore_metadata(folder, dataset.config.nbatch)
                integrity.remove_partial(folder, found)  # no writer runs now
            except Exception as e:
                _rank_zero_ready(path, rank, error=e)  # the other ranks stop too
                raise
        _rank_zero_ready(path, rank, error=None)
        if folder is None:
            folder = StoreFolder(path)
            lock.check_joined(folder, job, rank[0])
            info = _open_for_writing(folder, dataset, batches, rank[1], workers, create=False)
            stage = "writing"
        batches = info["batches"]
        total = slots_of(rank[0], rank[1], batches)
        mine = [i * rank[1] + rank[0] for i in range(total)]
        done = _committed(folder, mine, progress)
        already = int(done[mine].sum())
        start = time.perf_counter()
        stages = pipeline.Stages()
        loader = torch.utils.data.DataLoader(
            _Writer(dataset, folder, batches, rank, done, compression), batch_size=None,
            num_workers=num_workers,
            multiprocessing_context=_worker_start(dataset) if num_workers else None)
        bar = _progress(progress, total, already, path)
        try:
            for _, _, diverged, seconds in loader:
                stages.merge(seconds)
                bar.update(1)
                if diverged:
                    bar.set_postfix(diverged=diverged, refresh=False)
        finally:
            bar.close()
        if rank[1] > 1:
            torch.distributed.barrier()  # complete when every rank's part is; rank 0 unlocks
    except OSError as e:
        number, reason, filename = _os_error(e)
        raise OSError(number, f"write: {reason} while writing the store at {path!r}; "
                              f"{ownership.os_error_message(number, stage)}", filename) from e
    finally:
        if held is not None:
            held.release()
        if folder is not None:
            folder.close()
    written = Written(path)
    config = dataset.config
    written.report = pipeline.WriteReport(
        batches=int(total - already), steps=int(total - already) * config.nbatch * config.nstep,
        seconds=time.perf_counter() - start, writers=workers, stages=dict(stages.seconds),
        threads=pipeline.shard_threads())
    return written


def _writer_rank() -> tuple[int, int]:
    """(rank, world size) of this writer. Ranks of one store must agree on who they are and
    wait for each other before rank 0 releases the lock: several ranks write through a
    torch.distributed process group; torchrun's variables without one are refused (each
    rank would finish alone, and rank 0 report success while others' slots are missing)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    found = sharding.distributed_rank()  # the variables, checked
    if found is None or found[1] == 1:
        return found or (0, 1)
    raise ValueError(f"RANK={found[0]} and WORLD_SIZE={found[1]} are set, but no "
                     f"torch.distributed process group is initialized: the ranks writing one "
                     f"store must agree on it through one. Call "
                     f"torch.distributed.init_process_group() before simloader.write in every "
                     f"rank (start them with torchrun), or unset RANK and WORLD_SIZE to write "
                     f"from one process")


def _job_id(rank: tuple[int, int]) -> str:
    """The writing job's id, which the lock file names: rank 0's, handed to the other ranks
    through the process group (no two jobs ever share one)."""
    job = lock.new_job_id()
    if rank[1] > 1:
        box = [job]
        torch.distributed.broadcast_object_list(box, src=0)
        job = box[0]
    return job


def _os_error(e: OSError) -> tuple[Optional[int], str, Optional[str]]:
    """(errno, reason, file) of an OSError, also of one a DataLoader worker raised: torch
    re-raises it in this process as the same type around the worker's whole traceback, whose
    last line is the original error (the traceback stays reachable as the cause)."""
    if e.strerror is not None:
        return e.errno, e.strerror, e.filename
    said = str(e)
    found = re.findall(r"\[Errno (\d+)\] ([^\n]*?)(?:: '([^'\n]*)')?$", said, re.MULTILINE)
    if found:
        number, reason, filename = found[-1]
        return int(number), reason, filename or None
    return e.errno, said.strip().splitlines()[-1] if said.strip() else type(e).__name__, None


def _restore_metadata(folder: StoreFolder, nbatch: int) -> None:
    """Rank 0, holding the lock: an array whose metadata was removed or edited gets it back
    from the checksums' record (its slots' files are then checked as any other's)."""
    store = integrity.Store(folder, repair=True)
    for name in store.problems:
        if name == CHECKSUM:
            continue  # no record to restore from: `_committed` redoes every slot
        _ensure_groups(folder, name)
        where = name + "/zarr.json"
        kept = store.record[name]
        folder.write_json(where, {**kept, "shape": [store.batches * nbatch,
                                                    *kept["shape"][1:]]}, durable=True)
        folder.sync(folders_above(where))


def _committed(folder: StoreFolder, mine: list[int], progress: bool) -> np.ndarray:
    """Per slot of the store, whether it is committed and intact: this rank's committed
    slots are checked (sizes and every checksum); a damaged one loses its mark, durably, so
    that it is written again and no reader takes it meanwhile. Without the checksums'
    record (its metadata removed) no committed slot can be trusted: all are redone."""
    store = integrity.Store(folder, repair=True)
    done = np.zeros(store.batches, dtype=bool)
    done[store.slots] = True
    check = [s for s in mine if done[s]]
    if not check:
        return done
    if store.problems:
        damaged: dict[int, list[str]] = {slot: [] for slot in check}
    else:
        from tqdm import tqdm
        with tqdm(total=len(check), unit="slot", desc=f"check {folder.path}",
                  disable=not progress,
                  file=sys.stderr, leave=False) as bar:
            damaged = store.damaged(check, verify=True, progress=bar.update)
    for slot in damaged:
        marker = WRITTEN.shard_key(slot)
        folder.unlink(marker)
        folder.sync(folders_above(marker, WRITTEN.name)[:1])
        done[slot] = False
    return done


def _rank_zero_ready(path: str, rank: tuple[int, int],
                     error: Optional[BaseException]) -> None:
    """The other ranks of a job write once rank 0 holds the lock and made the root: rank 0
    says so (or that it failed) by a broadcast over the process group."""
    if rank[1] == 1:
        return
    backend = torch.distributed.get_backend()
    device = (torch.device("cuda", torch.cuda.current_device()) if "nccl" in str(backend)
              else torch.device("cpu"))
    flag = torch.tensor([0 if error is not None else 1], device=device)
    torch.distributed.broadcast(flag, src=0)
    if rank[0] != 0 and not int(flag.item()):
        raise lock.StoreLocked(f"rank 0 could not open the store at {path!r} for writing (it "
                               f"says why); held by {lock.describe(lock.holder(path))}")


def _worker_start(dataset: Any) -> Optional[str]:
    """How `write` starts its workers: fork unless the dataset renders (OpenGL's state does
    not survive a fork) or its engine does not fork safely (a GPU runtime, JAX), then
    spawn."""
    renders = any(o.rendered for o in dataset.config.observations)
    return "spawn" if renders or not dataset.engine.forks_safely else None


def _progress(enabled: bool, total: int, already: int, path: str):
    from tqdm import tqdm
    return tqdm(total=total, initial=already, unit="batch", desc=f"write {path}",
                disable=not enabled, file=sys.stderr, leave=False)

