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

from simloader.store import lock, ownership, pipeline
from simloader.store.folder import StoreFolder
from simloader.store.provenance import (StoreMismatch, differences, fingerprint,
                                        fingerprint_digest, new_identity, versions)
from simloader.store.frames import item_index, key_kinds, transition_indices
from simloader.batch import flat, nested
from simloader.store.reader import StoredDataset
from simloader.store.zarr_format import (ATTRIBUTE, FORMAT, MIXTURE_KIND, DamagedStore,
                                         store_part)

KIND = MIXTURE_KIND
TASKS = "tasks"  # the group of the members' stores


def is_mixture(dataset: Any) -> bool:
    from simloader.mixture import Mixture  # the store knows the mixture, not the reverse
    return isinstance(dataset, Mixture)


def counts(mixture: Any, batches: int) -> list[int]:
    """Per member, how many of its batches the mixture's first `batches` batches hold."""
    drawn = mixture.members(batches * mixture.group)
    return np.bincount(drawn, minlength=len(mixture.datasets)).tolist()


def task_path(root: str, name: str) -> str:
    return os.path.join(root, *task_name(name).split("/"))


def write_mixture(mixture: Any, path: str, *, batches: int, num_workers: int, progress: bool,
                  replace: bool, compression: Optional[str] = None) -> str:
    """`write(mixture, path, batches=)`: each member's batches into its own store under
    `path/tasks/`, under the root's lock (one job at a time, as any store), every file
    through the root's open folder (as a store's). The root names each member's store
    (its identity, drawn before the store is made, and its fingerprint's digest) before any
    is written: a reader refuses a `tasks/NAME` that is not the one the mixture wrote."""
    from simloader import sharding
    from simloader.store import writer
    found = sharding.distributed_rank()
    if (torch.distributed.is_available() and torch.distributed.is_initialized() and
            torch.distributed.get_world_size() > 1) or (found is not None and found[1] > 1):
        raise ValueError("write: a Mixture is written from one process (num_workers= "
                         "simulates and writes in parallel); several torchrun ranks writing "
                         "one mixture store are not supported")
    _check_names(mixture)  # before anything is made
    ownership.check_path(path)
    start = time.perf_counter()
    with StoreFolder(path, create=True) as folder:
        ownership.check_contents(folder, replace)
        with lock.WriterLock(folder, lock.new_job_id()):
            # a link is refused before anything is removed or written (as a store's are)
            kind = folder.kind(TASKS)
            if kind not in (None, "folder") or (kind == "folder" and any(
                    k == "link" for _, k, _ in folder.entries(TASKS))):
                raise ownership.NotAStore(f"path: the mixture store at {path!r} holds links "
                                          f"under {TASKS}/, which simloader never writes; "
                                          f"remove them")
            if replace:
                ownership.clear(folder)
            stored = folder.read_json("zarr.json")
            kept: dict = {}
            if stored is not None:
                kept = ((stored.get("attributes") or {}).get(ATTRIBUTE) or {})
                if kept.get("kind") != KIND:
                    raise StoreMismatch(f"the store at {path!r} holds one dataset's batches, "
                                        f"not a mixture's: write the mixture to a new path "
                                        f"(or replace=True)")
                mine = _root(mixture, batches, {})
                differ = [f"{k}: stored {kept.get(k)!r}, given {mine[k]!r}"
                          for k in ("tasks", "weights", "seed", "pad") if kept.get(k) != mine[k]]
                if differ:
                    raise StoreMismatch(f"the store at {path!r} holds another mixture; it "
                                        f"cannot be appended to ({'; '.join(differ)})")
            members = _members(mixture, folder, kept.get("members"))  # before anything
            mine = _root(mixture, max(batches, kept.get("batches", 0)), members)
            if stored is None:  # the store's own root first (a new store: no batch yet)
                folder.make_directories(TASKS)
                folder.write_json(TASKS + "/zarr.json", {
                    "zarr_format": 3, "node_type": "group", "attributes": {}}, durable=True)
            if stored is None or kept.get("members") != members:
                # the members named before any of their stores is made or grown
                folder.sync([TASKS])
                _write_root(folder, {**mine, "batches": kept.get("batches", 0),
                                     "counts": kept.get("counts", [0] * len(members))})
            reports = []
            for name, member, n in zip(mixture.names, mixture.datasets, mine["counts"]):
                if n:
                    options = {"compression": compression} if compression else {}
                    written = writer.write_zarr(member, task_name(name), batches=n,
                                                num_workers=num_workers, progress=progress,
                                                replace=False, member_of=folder,
                                                identity=members[name]["id"], **options)
                    reports.append(written.report)
            # the batches every task now holds: said once all are written (a refused or
            # killed write leaves the root as it was; each task's store says what it holds)
            if mine["batches"] != kept.get("batches") or kept.get("members") != members:
                _write_root(folder, mine)
    out = writer.Written(path)
    stages = pipeline.Stages()
    for r in reports:
        stages.merge(r.stages)
    out.report = pipeline.WriteReport(
        batches=sum(r.batches for r in reports), steps=sum(r.steps for r in reports),
        seconds=time.perf_counter() - start, writers=max(1, num_workers),
        stages=dict(stages.seconds), threads=max([r.threads for r in reports] or [1]))
    return out


def task_name(name: str) -> str:
    """Task `name`'s store, relative to the mixture store's root."""
    return f"{TASKS}/{store_part(name)}"


def _check_names(mixture: Any) -> None:
    """Every task's store has a folder of its own under `tasks/`: a name whose folder would
    be the group's own metadata, or a killed writer's leftover, is refused before anything
    is written."""
    for name in mixture.names:
        folder = store_part(name)
        if folder == "zarr.json" or ownership.LEFTOVER.search(folder):
            raise ValueError(f"datasets: the task name {name!r} is reserved in a mixture's "
                             f"store (tasks/{folder} is the group's own file); rename the "
                             f"task")


def _write_root(folder: StoreFolder, attribute: dict) -> None:
    folder.write_json("zarr.json", {
        "zarr_format": 3, "node_type": "group", "attributes": {ATTRIBUTE: attribute}},
        durable=True)
    folder.sync([""])


def _members(mixture: Any, folder: StoreFolder, recorded: Any) -> dict[str, dict]:
    """Per task, its store's identity and fingerprint's digest: those the root recorded
    (each existing store must still be that one), or those of a store written before roots
    recorded them, or a new identity for a store not made yet. A task's store of another
    configuration, or not the one recorded, is refused naming the task, before anything is
    written."""
    recorded = recorded if isinstance(recorded, dict) else {}
    out = {}
    for name, member in zip(mixture.names, mixture.datasets):
        mine = fingerprint(member)
        digest = fingerprint_digest(mine)
        meta = folder.read_json(task_name(name) + "/zarr.json") \
            if folder.kind(task_name(name)) == "folder" else None
        kept = ((meta or {}).get("attributes") or {}).get(ATTRIBUTE)
        was = recorded.get(name)
        if isinstance(kept, dict) and "fingerprint" in kept:
            differ = differences(kept["fingerprint"], mine)
            if differ:
                raise StoreMismatch(f"the store at {folder.path!r} holds another "
                                    f"configuration for task {name!r}; it cannot be "
                                    f"appended to ({'; '.join(differ)})")
            if isinstance(was, dict) and was.get("id") != kept.get("id"):
                raise StoreMismatch(member_refusal(folder.path, name, "identity",
                                                   kept.get("id"), was.get("id")))
            out[name] = {"id": kept.get("id"), "fingerprint": digest}
        else:
            out[name] = {"id": was.get("id") if isinstance(was, dict) else new_identity(),
                         "fingerprint": digest}
    return out


def member_refusal(path: str, name: str, what: str, found: Any, recorded: Any) -> str:
    return (f"the mixture store at {path!r}: its task {name!r} ({TASKS}/{store_part(name)}) "
            f"has {what} {found!r}, but the mixture recorded {recorded!r}: it is not the "
            f"store the mixture wrote (copied or replaced from another dataset?). Put the "
            f"task's own store back, or write the mixture again to a new path")


def _root(mixture: Any, batches: int, members: dict) -> dict:
    return {"format": FORMAT, "kind": KIND, "tasks": list(mixture.names),
            "weights": [float(w) for w in mixture.weights], "seed": mixture.seed,
            "pad": mixture.pad, "batches": batches, "counts": counts(mixture, batches),
            "describe": mixture.describe(), "versions": versions(), "members": members}


def mixture_root(path: str) -> Optional[dict]:
    """The root attribute of a mixture store at `path`, or None for any other folder."""
    if "\0" in path or not os.path.isdir(path):
        return None  # a file or nothing: StoredDataset says which
    try:
        with StoreFolder(path) as folder:
            kept = ownership.root_attribute(folder)
    except (ValueError, OSError):
        return None
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
        members = root.get("members") if isinstance(root.get("members"), dict) else None
        for name in self.names:
            where = task_path(self.path, name)
            if os.path.exists(os.path.join(where, "zarr.json")):
                # cameras= and the renderer's options: each task's store renders its own
                task = self.tasks[name] = StoredDataset(where, keys=keys, verify=verify,
                                                        **options)
                if members is not None:
                    _check_member(self.path, name, task.info, members.get(name))
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

    def transitions(self, *args: Any, **kwargs: Any) -> "MixturePattern":
        """Every task's `transitions(...)` in one dataset: its batches mix the tasks' rows,
        padded to the widest task, with `"task"` per row and `"mask/KEY"` where the widths
        differ (one task's alone: `tasks[NAME].transitions()`)."""
        parts = {n: self.tasks[n].transitions(*args, **kwargs) for n in self._present}
        return MixturePattern(self, parts)

    def windows(self, *args: Any, **kwargs: Any) -> "MixturePattern":
        """Every task's `windows(...)` in one dataset, with `"task"` per row (padded to the
        widest task where the store was written from `pad=True`), as `transitions`."""
        return MixturePattern(self, {n: self.tasks[n].windows(*args, **kwargs)
                                     for n in self._present})

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


def _check_member(path: str, name: str, info: dict, recorded: Any) -> None:
    """A task's store is the one the mixture's root names (its identity and its
    fingerprint's digest), or `DamagedStore` naming what differs."""
    if not isinstance(recorded, dict):
        raise DamagedStore(f"the mixture store at {path!r} records no store for its task "
                           f"{name!r}: its root was edited or damaged")
    digest = fingerprint_digest(info.get("fingerprint"))
    for what, found, kept in (("identity", info.get("id"), recorded.get("id")),
                              ("fingerprint", digest, recorded.get("fingerprint"))):
        if found != kept:
            raise DamagedStore(member_refusal(path, name, what, found, kept))


def _row(batch: Mapping[str, Any]) -> dict[str, Any]:
    """The only row of a batch of one (`params` nested)."""
    return {k: _row(v) if isinstance(v, Mapping) else v[0] for k, v in batch.items()}


def _batched(item: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """An item as a batch of one row, `params` flattened to `params/KEY` (`batch.flat`)."""
    return {name: value[None] for name, value in flat(item).items()}


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
    return nested(out)


class MixturePattern(torch.utils.data.Dataset):
    """A reading pattern (transitions, windows) of every task of a mixture's store, task
    after task (in the mixture's order): `gather(ks)` reads each task's part of `ks` with that
    task's own pattern and pads the rows together (`pad_rows`). `loader` is the patterns'
    loader, over all of them."""

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
                # masked per column: a window's frame axis leads (`frame_axes`), and
                # control with record_every > 1 is (steps, ncontrol)
                part = next(iter(self.parts.values()))
                framed = getattr(part, "frame_axes", 0) if key not in part.context else 0
                lead = len(found[0]) - 1 if key == "control" else framed
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
            block = first.block
            sampler: Any = orders.BlockOrder(len(self), batch_size, order, block, 8,
                                             drop_last, seed)
        else:
            sampler = TaskBatches([len(p) for p in self.parts.values()],
                                  [p.block for p in self.parts.values()],
                                  batch_size, order, drop_last, seed)
        from simloader.loaders import StatefulDataLoader as Loader
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

