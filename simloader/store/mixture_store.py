"""A `Mixture` in a store: `write(mixture, path, batches=N)` keeps each member's batches in a
store of its own, `path/tasks/NAME/` (the member's provenance, checks, resume and
`regenerate`, as any store's), and the root says which tasks in which order, their weights,
the schedule's seed and `pad`. `StoredMixture` reads it back as one dataset with `"task"`.

What is kept is what the mixture yields read with `num_workers=0` on one process: of its first
`N` batches (`N x len(datasets)` draws with `pad=True`), member `i` delivers its own first `n_i`
batches, so its store holds those `n_i` batches, written by the member's own writer. Writing
again with a larger `N` extends every member's store; the same `N` resumes them.
"""

from __future__ import annotations

import bisect
import functools
import os
import time
from collections.abc import Mapping, Sequence
from typing import Any, Optional

import numpy as np
import torch

from simloader.atomic import sync_directories
from simloader.store import lock, ownership, pipeline
from simloader.store.provenance import StoreMismatch, differences, fingerprint, versions
from simloader.store.reader import (OPENERS, StoredDataset, item_index, key_kinds, nest,
                                    transition_indices)
from simloader.store.zarr_format import (ATTRIBUTE, FORMAT, leaves, read_json, store_path,
                                         write_json)

KIND = "mixture"
TASKS = "tasks"  # the group of the members' stores


def is_mixture(dataset: Any) -> bool:
    from simloader.mixture import Mixture  # the store knows the mixture, not the reverse
    return isinstance(dataset, Mixture)


def counts(mixture: Any, batches: int) -> list[int]:
    """Per member, how many of its batches the mixture's first `batches` batches hold."""
    drawn = mixture.members(batches * mixture.group)
    return np.bincount(drawn, minlength=len(mixture.datasets)).tolist()


def task_path(root: str, name: str) -> str:
    return os.path.join(root, TASKS, store_path(name))


def write_mixture(mixture: Any, path: str, *, batches: int, num_workers: int, progress: bool,
                  replace: bool, compression: Optional[str] = None) -> str:
    """`write(mixture, path, batches=)`: each member's batches into its own store under
    `path/tasks/`, under the root's lock (one job at a time, as any store)."""
    from simloader import sharding
    from simloader.store import writer
    found = sharding.distributed_rank()
    if (torch.distributed.is_available() and torch.distributed.is_initialized() and
            torch.distributed.get_world_size() > 1) or (found is not None and found[1] > 1):
        raise ValueError("write: a Mixture is written from one process (num_workers= "
                         "simulates and writes in parallel); several torchrun ranks writing "
                         "one mixture store are not supported")
    ownership.check_target(path, replace)
    start = time.perf_counter()
    with lock.WriterLock(path, lock.new_job_id()):
        tasks = os.path.join(path, TASKS)
        # a link is refused before anything is removed or written (as a store's are)
        if os.path.lexists(tasks) and (os.path.islink(tasks) or any(
                os.path.islink(e.path) for e in os.scandir(tasks))):
            raise ownership.NotAStore(f"path: the mixture store at {path!r} holds links under "
                                      f"{TASKS}/, which simloader never writes; remove them")
        if replace:
            ownership.clear(path)
        mine = _root(mixture, batches)
        stored = read_json(os.path.join(path, "zarr.json"))
        if stored is not None:
            kept = ((stored.get("attributes") or {}).get(ATTRIBUTE) or {})
            if kept.get("kind") != KIND:
                raise StoreMismatch(f"the store at {path!r} holds one dataset's batches, not a "
                                    f"mixture's: write the mixture to a new path (or "
                                    f"replace=True)")
            differ = [f"{k}: stored {kept.get(k)!r}, given {mine[k]!r}"
                      for k in ("tasks", "weights", "seed", "pad") if kept.get(k) != mine[k]]
            if differ:
                raise StoreMismatch(f"the store at {path!r} holds another mixture; it cannot "
                                    f"be appended to ({'; '.join(differ)})")
            if kept.get("batches", 0) > batches:
                mine = _root(mixture, kept["batches"])
        _check_members(mixture, path)  # before anything is written
        if stored is None:  # the store's own root first (a new store: no batch yet)
            os.makedirs(tasks, exist_ok=True)
            write_json(os.path.join(tasks, "zarr.json"), {
                "zarr_format": 3, "node_type": "group", "attributes": {}}, durable=True)
            _write_root(path, _root(mixture, 0))
            sync_directories([tasks, path])
        reports = []
        for name, member, n in zip(mixture.names, mixture.datasets, mine["counts"]):
            if n:
                options = {"compression": compression} if compression else {}
                written = writer.write_zarr(member, task_path(path, name), batches=n,
                                            num_workers=num_workers, progress=progress,
                                            replace=False, **options)
                reports.append(written.report)
        # the batches every task now holds: said once all are written (a refused or killed
        # write leaves the root as it was; each task's store says what it holds)
        if stored is None or mine["batches"] != kept.get("batches"):
            _write_root(path, mine)
    out = writer.Written(path)
    stages = pipeline.Stages()
    for r in reports:
        stages.merge(r.stages)
    out.report = pipeline.WriteReport(
        batches=sum(r.batches for r in reports), steps=sum(r.steps for r in reports),
        seconds=time.perf_counter() - start, writers=max(1, num_workers),
        stages=dict(stages.seconds), threads=max([r.threads for r in reports] or [1]))
    return out


def _write_root(path: str, attribute: dict) -> None:
    write_json(os.path.join(path, "zarr.json"), {
        "zarr_format": 3, "node_type": "group", "attributes": {ATTRIBUTE: attribute}},
        durable=True)


def _check_members(mixture: Any, path: str) -> None:
    """Every task's store that exists holds its member's configuration (refused otherwise,
    naming the task and what differs), checked before any task is written."""
    for name, member in zip(mixture.names, mixture.datasets):
        meta = read_json(os.path.join(task_path(path, name), "zarr.json"))
        kept = ((meta or {}).get("attributes") or {}).get(ATTRIBUTE)
        if not isinstance(kept, dict) or "fingerprint" not in kept:
            continue
        differ = differences(kept["fingerprint"], fingerprint(member))
        if differ:
            raise StoreMismatch(f"the store at {path!r} holds another configuration for task "
                                f"{name!r}; it cannot be appended to ({'; '.join(differ)})")


def _root(mixture: Any, batches: int) -> dict:
    return {"format": FORMAT, "kind": KIND, "tasks": list(mixture.names),
            "weights": [float(w) for w in mixture.weights], "seed": mixture.seed,
            "pad": mixture.pad, "batches": batches, "counts": counts(mixture, batches),
            "describe": mixture.describe(), "versions": versions()}


def mixture_root(path: str) -> Optional[dict]:
    """The root attribute of a mixture store at `path`, or None for any other folder."""
    if not os.path.isdir(path):
        return None  # a file or nothing: StoredDataset says which
    try:
        meta = read_json(os.path.join(path, "zarr.json"))
    except (ValueError, OSError):
        return None
    kept = ((meta or {}).get("attributes") or {}).get(ATTRIBUTE) if isinstance(meta, dict) \
        else None
    return kept if isinstance(kept, dict) and kept.get("kind") == KIND else None


class StoredMixture(torch.utils.data.Dataset):
    """A mixture's store read back: item `i` is a trajectory of one task's store (the tasks in
    the mixture's order, each task's trajectories in its store's order) with `"task"`, the
    task's index; with the store written from `pad=True`, every item is padded to the widest
    task, with `"mask/KEY"` (as the mixture's batches were). `tasks` holds each task's own
    `StoredDataset`; `regenerate` and `transitions` work across them."""

    def __init__(self, path: str | os.PathLike, keys: Optional[Sequence[str]] = None,
                 verify: bool = False, **options: Any):
        self.path = os.fspath(path)
        root = mixture_root(self.path)
        if root is None:
            raise ValueError(f"path: {self.path!r} is not a mixture's store")
        self.info = root
        self.names = list(root["tasks"])
        self.pad = bool(root["pad"])
        self.tasks: dict[str, Any] = {}
        for name in self.names:
            where = task_path(self.path, name)
            if os.path.exists(os.path.join(where, "zarr.json")):
                # cameras= and the renderer's options: each task's store renders its own
                self.tasks[name] = StoredDataset(where, keys=keys, verify=verify, **options)
        self._index = {n: i for i, n in enumerate(self.names)}
        self._present = list(self.tasks)
        self._starts = np.cumsum([0] + [len(self.tasks[n]) for n in self._present]).tolist()

    def describe(self) -> str:
        return self.info["describe"]

    def __len__(self) -> int:
        return self._starts[-1]

    def locate(self, i: int) -> tuple[str, int]:
        """(task name, its trajectory) of item `i`."""
        i = item_index(i, len(self))
        k = bisect.bisect_right(self._starts, i) - 1
        return self._present[k], i - self._starts[k]

    def __getitem__(self, i: int) -> dict[str, Any]:
        name, j = self.locate(i)
        item = dict(self.tasks[name][j])
        task = self._index[name]
        if self.pad:
            return _row(pad_rows([(task, _batched(item))], self._plan))
        item["task"] = torch.tensor(task, dtype=torch.int64)
        return item

    def regenerate(self, mixture: Any, i: int) -> dict[str, Any]:
        """Item `i` simulated again by its member of `mixture` (the mixture that wrote the
        store: its tasks and their datasets), as `StoredDataset.regenerate`."""
        name, j = self.locate(i)
        if list(mixture.names) != self.names:
            raise ValueError(f"mixture: its tasks {list(mixture.names)} are not the store's "
                             f"{self.names}")
        again = dict(self.tasks[name].regenerate(mixture.datasets[self._index[name]], j))
        again["task"] = torch.tensor(self._index[name], dtype=torch.int64)
        return again

    def transitions(self, *args: Any, **kwargs: Any) -> "MixtureTransitions":
        """Every task's `transitions(...)` in one dataset: its batches mix the tasks' rows,
        padded to the widest task, with `"task"` per row and `"mask/KEY"` where the widths
        differ (one task's alone: `tasks[NAME].transitions()`)."""
        parts = {n: self.tasks[n].transitions(*args, **kwargs) for n in self._present}
        return MixtureTransitions(self, parts)

    @functools.cached_property
    def _plan(self) -> dict[str, tuple[tuple, torch.dtype, int]]:
        """Per stored key whose shape differs between the tasks (or that some tasks lack):
        the widest trailing shape and the dtype, so that every padded item has the same keys
        and shapes."""
        shapes: dict[str, list] = {}
        dtypes: dict[str, torch.dtype] = {}
        per_frame: set[str] = set()
        for stored in self.tasks.values():
            per_frame.update(key_kinds(stored)[0])
            for key in stored.keys:  # those asked for (keys=)
                shapes.setdefault(key, []).append(tuple(stored.metas[key]["shape"][1:]))
                dtypes[key] = torch.from_numpy(np.zeros(0, stored.layouts[key].dtype)).dtype
        out = {}
        for key, found in shapes.items():
            if len(set(found)) > 1 or len(found) < len(self.tasks):
                widest = tuple(max(s[d] for s in found) for d in range(len(found[0])))
                # a per-frame key's mask is per row, not per frame (as the mixture's); control
                # is one row per step
                lead = 1 if key in per_frame or key == "control" else 0
                out[key] = (widest, dtypes[key], lead)
        return out


def _row(batch: Mapping[str, Any]) -> dict[str, Any]:
    """The only row of a batch of one (`params` nested)."""
    return {k: _row(v) if isinstance(v, Mapping) else v[0] for k, v in batch.items()}


def _batched(item: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """An item as a batch of one row, `params` flattened to `params/KEY` (`leaves`)."""
    return {name: value[None] for name, value in leaves(item)}


def pad_rows(parts: Sequence[tuple[int, Mapping[str, torch.Tensor]]],
             plan: Optional[Mapping[str, tuple[tuple, torch.dtype, int]]] = None
             ) -> dict[str, Any]:
    """Row batches of several tasks in one: each key's rows concatenated, padded with zeros
    at the end of every trailing axis to the widest, `"task"` per row and `"mask/KEY"` (True
    on real columns) for each padded key; `params/KEY` nested back into `params`. `plan`
    ({key: (widest trailing shape, dtype, lead)}) pads and masks those keys always, whatever
    the parts hold, so that batches of any tasks have the same keys and shapes; their masks
    leave out the `lead` axes (frames, steps), as the mixture's batches do: `(rows,
    *widest[lead:])`."""
    plan = plan or {}
    if not parts:
        return {"task": torch.zeros(0, dtype=torch.int64)}
    keys = list(dict.fromkeys([k for _, p in parts for k in p] + list(plan)))
    rows = [len(next(iter(p.values()))) for _, p in parts]
    out: dict[str, Any] = {}
    for key in keys:
        values = [p.get(key) for _, p in parts]
        present = [v for v in values if v is not None]
        shapes = [tuple(v.shape[1:]) if v is not None else None for v in values]
        if key in plan:
            widest, dtype, lead = plan[key]
        else:
            rank = present[0].dim()
            widest = tuple(max(s[d] for s in shapes if s is not None) for d in range(rank - 1))
            dtype, lead = present[0].dtype, 0
        if key not in plan and all(s == widest for s in shapes):
            out[key] = torch.cat(present)
            continue
        value = torch.zeros((sum(rows), *widest), dtype=dtype)
        mask = torch.zeros((sum(rows), *widest[lead:]), dtype=torch.bool)
        at = 0
        for v, s, n in zip(values, shapes, rows):
            if v is not None:
                value[(slice(at, at + n), *(slice(0, m) for m in s))] = v
                mask[(slice(at, at + n), *(slice(0, m) for m in s[lead:]))] = True
            at += n
        out[key] = value
        out["mask/" + key] = mask
    out["task"] = torch.cat([torch.full((n,), t, dtype=torch.int64)
                             for (t, _), n in zip(parts, rows)])
    return nest(out)


class MixtureTransitions(torch.utils.data.Dataset):
    """The transitions of every task of a mixture's store, task after task (in the mixture's
    order): `gather(ks)` reads each task's part of `ks` with that task's own `gather` and pads
    the rows together (`pad_rows`). `loader` is `Transitions.loader`'s, over all of them."""

    def __init__(self, stored: StoredMixture, parts: Mapping[str, Any]):
        self.stored, self.parts = stored, dict(parts)
        self.names = list(parts)
        self.starts = np.cumsum([0] + [len(p) for p in parts.values()])

    def __len__(self) -> int:
        return int(self.starts[-1])

    def gather(self, ks: Sequence[int]) -> dict[str, Any]:
        """The transitions `ks` (negative counts from the end), in the order asked for."""
        ks = transition_indices(ks, len(self))
        which = np.searchsorted(self.starts, ks, side="right") - 1
        out, order = [], []
        for k, name in enumerate(self.names):
            at = np.flatnonzero(which == k)
            if len(at):
                out.append((self.stored._index[name],
                            self.parts[name].gather(ks[at] - self.starts[k])))
                order.append(at)
        batch = pad_rows(out, self._plan)
        if not order:
            return batch
        taken = np.concatenate(order)  # rows by task: back to the order of `ks`
        if (taken == np.arange(len(taken))).all():
            return batch
        inverse = torch.from_numpy(np.argsort(taken, kind="stable"))
        return {k: ({a: b[inverse] for a, b in v.items()} if isinstance(v, dict) else
                    v[inverse]) for k, v in batch.items()}

    @functools.cached_property
    def _plan(self) -> dict[str, tuple[tuple, torch.dtype, int]]:
        """The keys whose shapes differ between the tasks' transitions (or that some lack),
        with the widest shape: every batch then has the same keys and shapes, whichever
        tasks its rows come from (read from one transition of each task)."""
        samples = [p.gather([0]) for p in self.parts.values() if len(p)]
        keys = list(dict.fromkeys(k for sample in samples for k in sample))
        out = {}
        for key in keys:
            found = [tuple(x[key].shape[1:]) for x in samples if key in x]
            if len(set(found)) > 1 or len(found) < len(samples):
                dtype = next(x[key].dtype for x in samples if key in x)
                # control with record_every > 1: (steps, ncontrol), masked per column
                lead = len(found[0]) - 1 if key == "control" else 0
                out[key] = (tuple(max(f[d] for f in found) for d in range(len(found[0]))),
                            dtype, lead)
        return out

    def __getitem__(self, k: Any) -> dict[str, Any]:
        if isinstance(k, (int, np.integer)) and not isinstance(k, bool):
            return _row(self.gather([k]))
        return self.gather(k)

    def loader(self, batch_size: int, order: str = "quasi_random", drop_last: bool = False,
               seed: Optional[int] = None, **kwargs: Any) -> torch.utils.data.DataLoader:
        """Batches of `batch_size` transitions, as the store was written: a store of a
        `pad=True` mixture mixes every task's rows in each batch (`order` over all of them,
        as `Transitions.loader`); any other holds one task per batch, each task's batches in
        its own `order` and the tasks interleaved in a seeded order (`TaskBatches`). Either
        way a batch has `"task"` per row and every padded key's `"mask/KEY"`, so that all
        batches have the same keys and shapes. Resumes as `Transitions.loader` does."""
        from simloader.store import order as orders
        if self.stored.pad:
            first = next(iter(self.parts.values()))
            block = first.stored.nbatch * first.per
            sampler: Any = orders.BlockOrder(len(self), batch_size, order, block, 8,
                                             drop_last, seed)
        else:
            sampler = TaskBatches([len(p) for p in self.parts.values()],
                                  [p.stored.nbatch * p.per for p in self.parts.values()],
                                  batch_size, order, drop_last, seed)
        try:
            from torchdata.stateful_dataloader import StatefulDataLoader as Loader
        except ImportError:
            Loader = torch.utils.data.DataLoader
        return Loader(self, batch_size=None, sampler=sampler, **kwargs)


class TaskBatches(torch.utils.data.Sampler):
    """Batches of one task each, over tasks of `sizes` transitions laid end to end: every
    task's batches in its own `order.BlockOrder` (blocks of `blocks[i]`), and the tasks'
    batches interleaved in a new seeded order each epoch (each task's own order kept), so
    that an epoch reads every transition once. `state_dict()` / `load_state_dict()` resume
    an epoch after its last batch handed out, as `BlockOrder`'s do."""

    def __init__(self, sizes: Sequence[int], blocks: Sequence[int], batch_size: int,
                 order: str, drop_last: bool, seed: Optional[int]):
        from simloader.store import order as orders
        self.seed = int(torch.empty((), dtype=torch.int64).random_().item()) \
            if seed is None else seed
        self.starts = np.cumsum([0, *sizes])[:-1]
        self.tasks = [orders.BlockOrder(n, batch_size, order, b, 8, drop_last, self.seed + k)
                      for k, (n, b) in enumerate(zip(sizes, blocks))]
        self.epoch, self._resume = 0, 0
        self._progress: Optional[list[int]] = None

    def __len__(self) -> int:
        return sum(len(t) for t in self.tasks)

    def _plan(self, epoch: int) -> list[tuple[int, int]]:
        """(task, its batch) of every batch of the epoch, in the epoch's order."""
        labels = np.concatenate([np.full(len(t), k) for k, t in enumerate(self.tasks)])
        labels = np.random.default_rng([self.seed, epoch]).permutation(labels)
        seen = [0] * len(self.tasks)
        out = []
        for k in labels.tolist():
            out.append((k, seen[k]))
            seen[k] += 1
        return out

    def state_dict(self) -> dict[str, Any]:
        epoch, position = self._progress or (self.epoch, self._resume)
        return {"epoch": epoch, "position": position, "seed": self.seed, "batches": len(self)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not isinstance(state, dict) or state.get("batches") != len(self):
            raise ValueError(f"state: expected a TaskBatches.state_dict() of an epoch of "
                             f"{len(self)} batches, got {state!r}")
        self.seed, self.epoch, self._resume = (int(state["seed"]), int(state["epoch"]),
                                               int(state["position"]))
        self._progress = None

    def __iter__(self):
        epoch, start = self.epoch, self._resume
        self.epoch, self._resume = epoch + 1, 0
        progress = self._progress = [epoch, start]
        return self._batches(epoch, start, progress)

    def _batches(self, epoch: int, start: int, progress: list[int]):
        plan = self._plan(epoch)
        # each task's batches of this epoch (its BlockOrder's epoch `epoch`)
        per_task = []
        for task in self.tasks:
            task.epoch, task._resume = epoch, 0
            per_task.append(list(iter(task)))
        for k, b in plan[start:]:
            progress[1] += 1
            yield per_task[k][b] + self.starts[k]


OPENERS[KIND] = (lambda path: mixture_root(path) is not None, StoredMixture)
