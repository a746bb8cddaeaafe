"""`StoredDataset` and `Transitions`: a store read back as torch datasets, and the
regeneration of a stored trajectory from its provenance."""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Callable, Optional

import numpy as np
import torch

from simloader import known_faults, sharding
from simloader.layout import did_you_mean
from simloader.store import integrity, order as orders
from simloader.batch import flat, nested
from simloader.store.zarr_format import (CHECKSUM, PROVENANCE, WRITTEN, DamagedStore,
                                         batch_key)
from simloader.store.provenance import differences, fingerprint
from simloader.store import shards
from simloader.store.folder import StoreFolder
from simloader.store.frames import checked_keys, item_index, steps_and_frames, transition_indices
from simloader.store.shards import StoredArray
from simloader.store.windows import Episodes, Windows


# kinds of stores that read as another dataset than `StoredDataset`: {kind: (is_kind(path),
# opener(path, *args, **kwargs))}, filled by their modules (`mixture_store`)
OPENERS: dict[str, tuple[Callable[[str], bool], Callable[..., Any]]] = {}


class StoredDataset(torch.utils.data.Dataset):
    """A map-style dataset over a store that `simloader.write` made: item `i` is stored
    trajectory `i`, a dict of tensors keyed as the batch was (`params` a dict of them),
    without the leading `nbatch`.

    Only committed batch slots are seen, so a store still being written (or whose writer was
    killed) is readable. At open, every array's metadata is checked against the store's root
    and every committed slot's shard files against their layout and recorded sizes (links
    refused): a damaged store is refused with `DamagedStore`, naming each file and slot
    (writing again with the same dataset repairs it). Reading memory-maps raw shards (a
    trajectory's float arrays are slices of the files, copied once into the item's tensors)
    and decodes images per block of frames; at most `shards.MAX_OPEN` shards are open per
    process at any store size. Safe in DataLoader workers (files are opened in each process).

    Args:
      path: the store.
      keys: the batch keys to read (default: all but `provenance/`); `"params"` stands for
        all of `params/`.
      verify: also read every committed shard and check its CRC-32 (as `git fsck`); damaged
        slots are named.
      cameras: a `simloader.Camera` or a sequence of them: each item (and each transitions
        batch, for `s_t` and `next/` for `s_t+1`) then carries `"camera/NAME/rgb"` (and
        depth/segmentation as asked), rendered on access from the stored states with the
        model the store was simulated with (`simloader.store.pixels`): the pixels a
        streamed `Camera` of the CPU engine delivered for the same frames, bit for bit.
      backend: the engine whose renderer draws them: "cpu" (`mujoco.Renderer`, in this
        process or each DataLoader worker), "warp" (MuJoCo Warp's, on a CUDA device, every
        frame of a read batch one world: read with num_workers=0, or workers started with
        "spawn") or "auto" (by `device`).
      device: where the images are delivered (None: the host; a CUDA device for "warp").
      model: the model the store was simulated with (a name, an MJCF path, an MjModel, or
        the list of a `models=` / variants pool), for stores written before simloader kept
        it; checked against the store's digest.
    """

    def __init__(self, path: str | os.PathLike, keys: Optional[Sequence[str]] = None,
                 verify: bool = False, cameras: Any = None, backend: str = "auto",
                 device: Any = None, model: Any = None):
        self._open(path, keys, verify)
        self.cameras = None
        if cameras is not None:
            from simloader.store import pixels
            self.cameras = pixels.StoredCameras(self, cameras, backend, device, model)

    def __new__(cls, path: Any = None, *args: Any, **kwargs: Any) -> Any:
        # a store of another kind (a mixture's store of stores: `mixture_store`) reads as
        # the dataset its kind registered in `OPENERS`
        if cls is StoredDataset and isinstance(path, (str, os.PathLike)):
            for kind, (is_kind, opener) in OPENERS.items():
                if is_kind(os.fspath(path)):
                    return opener(path, *args, **kwargs)
        return super().__new__(cls)

    def _open(self, path: str | os.PathLike, keys: Optional[Sequence[str]],
              verify: bool) -> None:
        self.path = os.fspath(path)
        if not isinstance(verify, bool):
            raise ValueError(f"verify: expected True or False, got {verify!r}")
        if "\0" in self.path:
            raise ValueError(f"path: {self.path!r} holds a NUL character, which no file name "
                             f"can")
        if not os.path.exists(self.path):
            raise ValueError(f"path: {self.path!r} does not exist; expected a store folder "
                             f"that simloader.write made")
        if not os.path.isdir(self.path):
            raise ValueError(f"path: {self.path!r} is a file, not a store folder (simloader."
                             f"write makes a folder: a zarr v3 group)")
        self.folder = folder = StoreFolder(self.path)
        self.store = store = integrity.Store(folder)
        self.info = store.info
        # the identity it was opened with, confirmed whenever a shard is opened
        self.opened = shards.OpenedStore(folder, store.info.get("id"))
        self.layouts = {batch_key(p, store.survey.metas[p]): layout
                        for p, layout in store.layouts.items()
                        if p not in (WRITTEN.name, CHECKSUM)}
        available = [n for n in self.layouts if not n.startswith("provenance/")]
        if keys is None:
            names = available
        else:
            names = []
            for key in keys:
                found = [n for n in available if n == key or n.startswith(key + "/")]
                if not found:
                    raise KeyError(f"keys: the store has no key {key!r}"
                                   f"{did_you_mean(key, available)}; it has {sorted(available)}")
                names += found
        self.keys = sorted(set(names))
        self.nbatch = store.nbatch
        self.slots = store.slots  # committed batch slots, in order
        self.metas = {k: store.survey.metas[l.path] for k, l in self.layouts.items()}
        damaged = store.damaged(verify=verify, progress=None)
        if damaged:
            raise DamagedStore(integrity.describe_damage(self.path, damaged))
        # judged once (a store from before faults were recorded is judged by its models,
        # which are read for it)
        from simloader.store import pixels
        self.known_fault: Optional[str] = known_faults.stored_warning(
            self.info, models=lambda: pixels.kept_models(self))
        if self.known_fault is not None:
            warnings.warn(f"StoredDataset: {self.path}: {self.known_fault}",
                          known_faults.KnownFaultWarning, stacklevel=3)

    def __len__(self) -> int:
        return len(self.slots) * self.nbatch

    def describe(self) -> str:
        """What the stored batches hold (the writer's dataset's `describe()`: which columns
        of each key mean what), and a known fault of the simulator it was written under."""
        said, faulted = self.info["describe"], self.known_fault
        return said if faulted is None or "known fault" in said else f"{said}\n{faulted}"

    @functools.cached_property
    def _arrays(self) -> dict[str, StoredArray]:
        return {k: StoredArray(self.opened, layout) for k, layout in self.layouts.items()}

    def arrays(self) -> dict[str, StoredArray]:
        """Every array of the store, by batch key (shards are opened at their first read,
        in each process, and closed least recently used first)."""
        return self._arrays

    def locate(self, i: int) -> tuple[int, int]:
        """(batch slot, row) of stored trajectory `i`."""
        i = item_index(i, len(self))
        return int(self.slots[i // self.nbatch]), i % self.nbatch

    def read(self, i: int, names: Iterable[str]) -> dict[str, np.ndarray]:
        slot, row = self.locate(i)
        arrays = self.arrays()
        return {n: arrays[n].trajectory(slot, row) for n in names}

    def __getitem__(self, i: int) -> dict[str, Any]:
        item = {n: torch.from_numpy(np.array(a)) for n, a in self.read(i, self.keys).items()}
        if self.cameras is not None:
            states = self.read(i, ["state"])["state"]
            i = item_index(i, len(self))
            for key, frames in self.cameras.frames(states[None], np.array([i])).items():
                item[key] = frames[0]
        return nested(item)

    def provenance(self, i: int) -> dict[str, int]:
        """Where stored trajectory `i` comes from in the seeded stream: rank, batch (the
        rank's batch index), row, and the DataLoader workers that wrote it."""
        return {p: int(v) for p, v in self.read(i, ["provenance/" + p for p in PROVENANCE]
                                                ).items() for p in [p.split("/")[1]]}

    def transitions(self, state: str | Sequence[str] = "state", diverged: str = "drop",
                    context: str | Sequence[str] = ()) -> "Transitions":
        """The stored trajectories as transitions `(s_t, a_t, s_t+1)` (see `Transitions`).

        Args:
          state: the per-frame keys (arrays `ntrajectories x nframes x ...`) paired frame by
            frame.
          diverged: `"drop"` leaves out the trajectories flagged `diverged` (or `overflow`):
            what follows an instability is not physics to learn. `"keep"` keeps them.
          context: per-trajectory keys (`params/...`, `initial_state`, `diverged`, ...: one
            value per trajectory) that each transition carries as its trajectory's constant
            (`"params"` stands for all of `params/`).

        Raises:
          KeyError: a key the store lacks, or of the other kind (a per-trajectory key in
            `state`, a per-frame one in `context`).
          ValueError: the store has no committed batch slot yet.
        """
        if diverged not in ("drop", "keep"):
            raise ValueError(f"diverged: expected 'drop' or 'keep', got {diverged!r}")
        return Transitions(self, (state,) if isinstance(state, str) else tuple(state),
                           drop_flagged=diverged == "drop",
                           context=(context,) if isinstance(context, str) else tuple(context))

    def windows(self, length: int, *, state: str | Sequence[str] = "state",
                context: str | Sequence[str] = (), ends: str = "cross",
                actions: str = "produced", diverged: str = "drop") -> "Windows":
        """Every window of `length` consecutive frames (see `simloader.store.windows`, whose
        table maps DreamerV3's, TD-MPC2's, torchrl's and LeRobot's conventions to `ends=` and
        `actions=`). A trajectory's frames are its `initial_state` (`first=True`) and its
        stored frames; a store written with `continue_episodes=True` is read as streams (the
        batches of one rank, worker and row joined in order); a window never spans two.

        Args:
          length: frames per window.
          state: the per-frame keys each window holds (as `transitions`).
          context: per-trajectory keys, one value per window.
          ends: "cross" (DreamerV3), "inside" (TD-MPC2, `SliceSampler(strict_length=True)`)
            or "pad" (LeRobot: `mask` False past the episode's end).
          actions: "produced" (the row that produced frame t, NaN at a `first` frame) or
            "next" (the row applied after frame t; zeros after an episode's last frame).
          diverged: "drop" leaves out the trajectories flagged diverged (a continued stream
            is cut there); "keep" keeps them.
        """
        return Windows(self, length, (state,) if isinstance(state, str) else tuple(state),
                       ends, actions, diverged,
                       (context,) if isinstance(context, str) else tuple(context))

    def episodes(self, *, state: str | Sequence[str] = "state",
                 context: str | Sequence[str] = (), actions: str = "produced",
                 diverged: str = "drop") -> "Episodes":
        """Whole episodes (variable length, split at resets): item `i` a dict of
        `(length, ...)` tensors with a window's keys (see `windows`)."""
        return Episodes(self, (state,) if isinstance(state, str) else tuple(state), diverged,
                        (context,) if isinstance(context, str) else tuple(context), actions)

    def flagged(self) -> np.ndarray:
        """Per stored trajectory: flagged `diverged` or `overflow` (bool); read slot by slot
        through the bounded table of open shards."""
        arrays = [a for n, a in self.arrays().items() if n in ("diverged", "overflow")]
        out = np.zeros(len(self), dtype=bool)
        for k, slot in enumerate(self.slots):
            for array in arrays:
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
        differ = differences(self.info["fingerprint"], fingerprint(dataset))
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
        # a batch's draws depend on (seed, rank, index) only; the worker replays its stream
        shard = sharding.Shard(rank=rank, world_size=rank + 1, worker=index % workers,
                               num_workers=workers)
        batch = None
        for _, batch, _ in dataset.stream(dataset.make_backend(shard), indices):
            pass
        flat_batch = flat(batch)
        row = where["row"]
        out = {}
        for name in self.keys:
            value = flat_batch[name]
            out[name] = value[row] if value.ndim and value.shape[0] == self.nbatch \
                else value.expand(self.nbatch)[row]
        return nested({n: v.detach().cpu().clone() for n, v in out.items()})


def _take(rows: np.ndarray, at: np.ndarray, out: np.ndarray) -> None:
    """`out[:] = rows[at]` (rows of a 2-D view of a shard) with no temporary: mode "clip"
    skips the bounds pass that buffers `out`. The indices are in range by construction (the
    keys' frame axes are checked against the store's root when a `Transitions` is made);
    they are held to it here too (a min and a max), so that a bug raises instead of
    clipping silently to the last row."""
    if len(at) and (at.min() < 0 or at.max() >= len(rows)):
        bad = int(at[(at < 0) | (at >= len(rows))][0])
        raise IndexError(f"Transitions: row {bad} of a shard of {len(rows)} rows; this is a "
                         f"bug in simloader, please report it")
    if rows.shape[1]:  # a key without values (sensordata of a model without sensors)
        np.take(rows, at, axis=0, out=out.reshape(-1, rows.shape[1]), mode="clip")


class Transitions(torch.utils.data.Dataset):
    """The transitions of a store: item `k` is `{KEY: s_t, "control": a_t, "next/KEY": s_t+1}`
    for every state key, over the trajectories not flagged diverged (by default). With
    `record_every = k` the action is the `k` control rows between two frames
    (`k x ncontrol`). The first frame's predecessor is the initial state for the
    key `"state"` (`initial_state`), so a trajectory gives `nframes` transitions; other keys
    have no stored initial value and give `nframes - 1`. Each `context` key (a per-trajectory
    value: `params/...`, ...) is in every item too, its trajectory's value. In a store of
    episodes that end (`terminate=`: a stored `first`), a frame is never paired with the
    fresh initial state that follows it: the transitions into a `first` frame are left out.
    """

    def __init__(self, stored: StoredDataset, keys: tuple[str, ...], drop_flagged: bool,
                 context: tuple[str, ...] = ()):
        if not len(stored.slots):
            raise ValueError(
                f"transitions: the store at {stored.path!r} has no committed batch slot yet "
                f"(none of its {stored.info['batches']} slot(s) is marked written: its writer "
                f"was stopped before its first batch was complete, or the marks were "
                f"removed); there is nothing to pair. Calling simloader.write with the same "
                f"dataset writes it")
        constants = checked_keys(stored, keys, context)
        self.stored = stored
        self.keys = keys
        self.context = tuple(constants)
        self.every = int(stored.info["record_every"])
        nstep, self.nframes = steps_and_frames(stored)
        # every index `gather` takes is then in range: frames of `nframes`, controls of nstep
        if stored.metas["control"]["shape"][1] != nstep:
            raise DamagedStore(f"{stored.layouts['control'].file}: shape "
                               f"{stored.metas['control']['shape']}, expected {nstep} control "
                               f"rows per trajectory (nstep in the store's root)")
        self.first = 0 if keys == ("state",) else 1  # frame 0's predecessor is stored
        self.per = self.nframes - self.first
        self.drop_flagged = drop_flagged
        self.will_need = False  # read whole shards ahead (set by `loader` for block orders)

    @functools.cached_property
    def trajectories(self) -> np.ndarray:
        """The stored trajectories whose transitions these are, read at the first use, not
        when the view is made (it reads the flags of every slot)."""
        return (np.flatnonzero(~self.stored.flagged()) if self.drop_flagged else
                np.arange(len(self.stored)))

    @functools.cached_property
    def pairs(self) -> Optional[np.ndarray]:
        """In a store of episodes that end (a stored `first`), the transitions that are
        physics, as `position * nframes + frame` (position in `trajectories`, frame the
        transition's target), ascending; None in a store without resets (all of them). Read
        slot by slot at the first use."""
        if "first" not in self.stored.layouts:
            return None
        first, nbatch = self.stored.arrays()["first"], self.stored.nbatch
        kept = self.trajectories
        out = []
        for k, slot in enumerate(self.stored.slots):
            lo, hi = np.searchsorted(kept, [k * nbatch, (k + 1) * nbatch])
            if lo == hi:
                continue
            flags = first.slot(int(slot))[kept[lo:hi] % nbatch, self.first:]
            position, frame = np.nonzero(~flags)
            out.append((lo + position) * self.nframes + frame + self.first)
        return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)

    def locate(self, ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(stored trajectory, target frame) of transitions `ks` (in range)."""
        if self.pairs is not None:
            position, frames = np.divmod(self.pairs[ks], self.nframes)
        else:
            position, frames = np.divmod(ks, self.per)
            frames = frames + self.first
        return self.trajectories[position], frames

    def __len__(self) -> int:
        if self.pairs is not None:
            return len(self.pairs)
        return len(self.trajectories) * self.per

    def __getitem__(self, k: int | Sequence[int]) -> dict[str, torch.Tensor]:
        """Transition `k` (negative counts from the end; `IndexError` past it, which ends
        iteration), or for a sequence of indices the batch of them (what `loader`'s batch
        sampler asks for: no per-item tensors, no collation)."""
        if isinstance(k, (int, np.integer)) and not isinstance(k, bool):
            return {n: v[0] for n, v in self.gather([k]).items()}
        return self.gather(k)

    def __getitems__(self, ks: Sequence[int]) -> list[dict[str, torch.Tensor]]:
        """A DataLoader's batch (`batch_size=B`): the items as views of one gather, which
        the default collation stacks again. `loader()` skips both."""
        out = self.gather(ks)
        return [dict(zip(out, values)) for values in zip(*(v.unbind(0) for v in out.values()))]

    def loader(self, batch_size: int, order: str = "quasi_random", drop_last: bool = False,
               window: Optional[int] = None, seed: Optional[int] = None,
               shuffle: Optional[bool] = None, **kwargs: Any) -> torch.utils.data.DataLoader:
        """A DataLoader of batches of `batch_size` transitions, each read with one gather
        per key and batch slot (a batch sampler hands the dataset all of a batch's indices,
        `batch_size=None`: no per-item tensors are made or collated).

        Each iteration is one epoch, in a new order drawn from `seed` and the epoch's number.
        With torchdata installed the loader is its `StatefulDataLoader`, which resumes:
        `loader.state_dict()` taken after any batch, loaded into a loader made the same way
        (`load_state_dict`, even in a new process, with `num_workers` as it was: a state of
        another `num_workers` is refused by name), makes the
        next iteration deliver exactly the rest of that epoch, bit for bit, and the
        iterations after it the epochs that follow (the order's seed is in the state, so
        `seed=None` resumes too). The order's own state is `loader.sampler.state_dict()` (a
        `simloader.store.order.BlockOrder`: the epoch, the batches handed out of it, the
        seed). Without torchdata it is a plain `torch.utils.data.DataLoader`, which does not
        resume.

        Args:
          order: `"quasi_random"` (default: blocks of one batch slot's transitions in
            shuffled order, `window` blocks shuffled together; an epoch over a store bigger
            than memory reads each shard once, whole: see `simloader.store.order`),
            `"random"` (a full permutation) or `"sequential"`.
          window: blocks shuffled together (default: as many as the open-shard table holds).
          seed: the orders' seed (default: drawn from torch's generator, as `shuffle=True`).
          shuffle: the older spelling: True is `order="random"`, False `"sequential"`.
          kwargs: to the DataLoader (`num_workers=`, ...).
        """
        if shuffle is not None:
            order = "random" if shuffle else "sequential"
        return orders.pattern_loader(self, len(self), batch_size, order, self.block, window,
                                     drop_last, seed, len(self.keys) + 2, kwargs,
                                     ahead=self._read_ahead)

    @property
    def block(self) -> int:
        """The transitions of one batch slot (where none were dropped), which a
        quasi-random order reads as a block (one shard per array)."""
        return self.stored.nbatch * self.per

    def _read_ahead(self, blocks: np.ndarray, block: int) -> None:
        """The shard files of the blocks of transitions starting at `blocks`, read into the
        page cache in the background (see `order.BlockOrder`)."""
        firsts = np.asarray(blocks, dtype=np.int64)
        lasts = np.minimum(firsts + block, len(self)) - 1
        rows = np.concatenate([np.arange(*(self.locate(np.array([a, b]))[0] + [0, 1]))
                               for a, b in zip(firsts, lasts) if a <= b])
        slots = np.unique(self.stored.slots[rows // self.stored.nbatch])
        arrays = self.stored.arrays()
        names = [*self.keys, "control", "initial_state", *self.context]
        shards.read_ahead([arrays[n].layout.shard_file(self.stored.path, int(slot))
                           for slot in slots for n in names if not arrays[n].layout.empty])

    def gather(self, ks: Sequence[int]) -> dict[str, torch.Tensor]:
        """The transitions `ks` as a dict of tensors `len(ks) x ...`: per key and batch slot
        one `np.take` from the memory-mapped shard straight into the batch's tensor (indices
        in increasing order, as `loader` hands them, need no reordering afterwards)."""
        ks = transition_indices(ks, len(self))
        ascending = bool((ks[1:] >= ks[:-1]).all())
        order = None if ascending else np.argsort(ks, kind="stable")
        if order is not None:
            ks = ks[order]
        trajectories, frames = self.locate(ks)
        nbatch = self.stored.nbatch
        slots = self.stored.slots[trajectories // nbatch]
        rows = trajectories % nbatch
        arrays = self.stored.arrays()
        columns = self._allocate(len(ks), arrays)
        filled = {k: v.numpy() for k, v in columns.items()}  # the same memory, for numpy
        steps = np.arange(self.every)
        bounds = np.flatnonzero(slots[1:] != slots[:-1]) + 1
        for a, b in zip(np.concatenate([[0], bounds]), np.concatenate([bounds, [len(ks)]])):
            slot, r, f = int(slots[a]), rows[a:b], frames[a:b]
            for key in self.keys:
                seq = arrays[key].slot(slot, self.will_need)  # nbatch x nframes x ...
                flat = seq.reshape(seq.shape[0] * seq.shape[1], -1)
                at = r * seq.shape[1] + f
                _take(flat, at, filled["next/" + key][a:b])
                _take(flat, at - (f > 0), filled[key][a:b])  # frame 0: itself, fixed below
                if key == "state" and (f == 0).any():
                    first = np.flatnonzero(f == 0)
                    filled[key][a + first] = arrays["initial_state"].slot(
                        slot, self.will_need)[r[first]]
            control = arrays["control"].slot(slot, self.will_need)  # nbatch x nstep x ncontrol
            flat = control.reshape(control.shape[0] * control.shape[1], -1)
            at = (r * control.shape[1] + f * self.every)[:, None] + steps
            _take(flat, at.reshape(-1), filled["control"][a:b])
            for key in self.context:  # nbatch x ...: the trajectory's row
                seq = arrays[key].slot(slot, self.will_need)
                _take(seq.reshape(seq.shape[0], -1), r, filled[key][a:b])
        cameras = self.stored.cameras
        if cameras is not None:  # the frames of s_t and s_t+1, rendered from the states
            now, after = self._states(filled, slots, rows, frames)
            pair = np.stack([now, after], axis=1)  # (n, 2, nstate)
            for key, images in cameras.frames(pair, trajectories).items():
                columns[key] = images[:, 0].contiguous()
                columns["next/" + key] = images[:, 1].contiguous()
        if order is not None:  # back to the order asked for
            inverse = np.empty_like(order)
            inverse[order] = np.arange(len(order))
            columns = {k: v[torch.from_numpy(inverse)] for k, v in columns.items()}
        return columns

    def _states(self, filled: Mapping[str, np.ndarray], slots: np.ndarray, rows: np.ndarray,
                frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The FULLPHYSICS states of each transition's two frames (`state` and `next/state`
        where the view pairs them, else read; frame 0's predecessor is the initial state)."""
        if "state" in self.keys:
            return filled["state"], filled["next/state"]
        arrays = self.stored.arrays()
        now = np.empty((len(rows), arrays["state"].layout.trailing[-1]))
        after = np.empty_like(now)
        # each slot read once per call: a compressed slot is decoded whole
        read: dict[tuple[str, int], np.ndarray] = {}

        def rows_of(name: str, slot: int) -> np.ndarray:
            if (name, slot) not in read:
                read[name, slot] = arrays[name].slot(slot)
            return read[name, slot]

        for k, (slot, r, f) in enumerate(zip(slots, rows, frames)):
            seq = rows_of("state", int(slot))
            after[k] = seq[r, f]
            now[k] = seq[r, f - 1] if f > 0 else rows_of("initial_state", int(slot))[r]
        return now, after

    def _allocate(self, n: int, arrays: Mapping[str, StoredArray]) -> dict[str, torch.Tensor]:
        """The batch's tensors, those of one dtype laid back to back in one storage: a
        DataLoader worker hands a storage over through shared memory, one per dtype instead
        of one per key (on 2 cores that hand-over cost more than the gather)."""
        control = arrays["control"].trailing[1:]
        shapes = {**{k: (arrays[k].trailing[1:], arrays[k].dtype) for k in self.keys},
                  "control": (control if self.every == 1 else (self.every, *control),
                              arrays["control"].dtype),
                  **{"next/" + k: (arrays[k].trailing[1:], arrays[k].dtype) for k in self.keys},
                  **{k: (arrays[k].trailing, arrays[k].dtype) for k in self.context}}
        out = {}
        for dtype in {d for _, d in shapes.values()}:
            names = [k for k, (_, d) in shapes.items() if d == dtype]
            sizes = [n * int(np.prod(shapes[k][0], dtype=np.int64)) for k in names]
            flat = torch.from_numpy(np.empty(sum(sizes), dtype=dtype.newbyteorder("=")))
            for name, part in zip(names, flat.split(sizes)):
                out[name] = part.view(n, *shapes[name][0])
        return {k: out[k] for k in shapes}  # in order: states, control, next states, context

