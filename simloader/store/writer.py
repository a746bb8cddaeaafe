"""`write`: a dataset's batches into a store, by workers and ranks that never coordinate."""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterator, Mapping
from typing import Any, Optional

import numpy as np
import torch

from simloader import sharding
from simloader.store.format import (ATTRIBUTE, FORMAT, PROVENANCE, WRITTEN, ArraySpec, leaves,
                                    read_json, safe_name, specs_of, write_json, write_shard,
                                    written_slots, zstd)
from simloader.store.provenance import SIMULATING, StoreMismatch, differences, provenance


def _open_for_writing(path: str, dataset: Any, batches: int, ranks: int) -> dict:
    """Creates the store's root, or checks that an existing one holds this configuration and
    was written by as many ranks, and grows its size to `batches` slots. Every writer does
    the same, with the same result."""
    mine = {**provenance(dataset, batches), "ranks": ranks}
    root = read_json(os.path.join(path, "zarr.json"))
    if root is not None:
        stored = root.get("attributes", {}).get(ATTRIBUTE)
        if stored is None or stored.get("format") != FORMAT:
            raise StoreMismatch(f"path: {path!r} is not a simloader store of format {FORMAT} "
                                f"(its root has no {ATTRIBUTE!r} attribute of that format)")
        differ = differences(stored["fingerprint"], mine["fingerprint"])
        if differ:
            raise StoreMismatch(f"path: the store at {path!r} holds another configuration; "
                                f"it cannot be appended to ({'; '.join(differ)})")
        stale = [f"{k} {stored['versions'].get(k)} (now {mine['versions'].get(k)})"
                 for k in SIMULATING if stored["versions"].get(k) != mine["versions"].get(k)]
        if stale:
            raise StoreMismatch(f"path: the store at {path!r} was simulated by other versions "
                                f"({', '.join(stale)}); its trajectories would not continue "
                                f"the same stream; write to a new path")
        if stored.get("ranks") != ranks:
            # slot i * ranks + rank: another number of ranks would put batches the store
            # holds already into other slots (a trajectory twice, another never)
            raise StoreMismatch(f"path: the store at {path!r} is written by "
                                f"{stored.get('ranks')} rank(s) (torchrun processes); resume "
                                f"or extend it with {stored.get('ranks')}, not {ranks}, or "
                                f"write to a new path")
        mine["batches"] = max(batches, stored["batches"])
        mine["describe"] = stored["describe"]
    if root is None or mine["batches"] != root["attributes"][ATTRIBUTE]["batches"]:
        write_json(os.path.join(path, "zarr.json"), {
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
            write_json(group, {"zarr_format": 3, "node_type": "group", "attributes": {}})
    where = os.path.join(path, spec.name, "zarr.json")
    wanted = spec.metadata(ntrajectories)
    existing = read_json(where)
    if existing is not None:
        if {**existing, "shape": None} != {**wanted, "shape": None}:
            raise StoreMismatch(f"path: the store's array {spec.name!r} has shape "
                                f"{existing['shape']} and dtype {existing['data_type']}; "
                                f"this dataset's batches give {wanted['shape']} and "
                                f"{wanted['data_type']}")
        if existing["shape"][0] >= ntrajectories:
            return
    write_json(where, wanted)


def slots_of(rank: int, world: int, batches: int) -> int:
    """How many batch indices rank `rank` of `world` writes: those with `i * world + rank <
    batches`."""
    return max(0, math.ceil((batches - rank) / world))


class _Writer(torch.utils.data.IterableDataset):
    """Simulates this worker's missing slots and writes each, yielding a receipt per batch
    (slot, trajectories, diverged): the batches themselves never cross the worker's queue."""

    def __init__(self, dataset: Any, path: str, batches: int, rank: tuple[int, int],
                 done: np.ndarray):
        """`done`: the slots complete when `write` began (each slot has one writer, so no
        other writer completes one of this worker's meanwhile)."""
        self.dataset, self.path, self.batches, self.rank = dataset, path, batches, rank
        self.done = done

    def __iter__(self) -> Iterator[tuple[int, int, int]]:
        ds, done = self.dataset, self.done
        shard = sharding.current_shard(self.rank)
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
    for name, value in leaves(batch):
        spec = specs[safe_name(name)]
        rows = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
        if spec.trailing == () and np.ndim(rows) == 0:  # one per batch: one per trajectory
            rows = np.full(nbatch, rows, dtype=spec.dtype)
        write_shard(path, spec, slot, rows)
    for p, value in zip(PROVENANCE, (rank, index, None, num_workers)):
        rows = np.arange(nbatch) if p == "row" else np.full(nbatch, value)
        write_shard(path, specs["provenance/" + p], slot, rows)
    write_shard(path, WRITTEN, slot, np.ones(1, dtype=bool))  # last: the slot is complete


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

    `format="minari"`: a Minari dataset (see `simloader.store.minari`), named after the last
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
        from simloader.store import minari
        return minari.write(dataset, path, batches=batches, progress=progress,
                            metadata=provenance(dataset, batches))
    if format != "zarr":
        raise ValueError(f"format: expected 'zarr' or 'minari', got {format!r}")
    if any(o.rendered for o in dataset.config.observations):
        zstd()  # images are compressed: refuse now, naming the extra, not at the first batch
    rank = sharding.distributed_rank() or (0, 1)
    try:
        info = _open_for_writing(path, dataset, batches, rank[1])
        batches = info["batches"]
        total = slots_of(rank[0], rank[1], batches)
        done = written_slots(path, batches)
        already = int(sum(done[i * rank[1] + rank[0]] for i in range(total)))
        loader = torch.utils.data.DataLoader(
            _Writer(dataset, path, batches, rank, done), batch_size=None,
            num_workers=num_workers,
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

