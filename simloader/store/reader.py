"""`StoredDataset`: a store read back as a torch dataset (a trajectory an item), its reading
patterns (`transitions`, `windows`, `episodes`: `simloader.store.pattern`), and the
regeneration of a stored trajectory from its provenance."""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Iterable, Sequence
from typing import Any, Optional

import numpy as np
import torch

from simloader import known_faults, sharding
from simloader.layout import did_you_mean
from simloader.store import integrity, ownership
from simloader.batch import flat, nested
from simloader.store.zarr_format import (CHECKSUM, MIXTURE_KIND, PROVENANCE, WRITTEN,
                                         DamagedStore, batch_key)
from simloader.store.provenance import differences, fingerprint
from simloader.store import shards
from simloader.store.folder import StoreFolder
from simloader.store.frames import item_index, steps_and_frames
from simloader.store.shards import StoredArray
from simloader.store.transitions import Transitions
from simloader.store.windows import Episodes, Windows


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
        kept = ownership.root_attribute(folder)
        if isinstance(kept, dict) and kept.get("kind") == MIXTURE_KIND:
            folder.close()
            raise ValueError(f"path: {self.path!r} holds a mixture's store (one store per task "
                             f"under tasks/), not one stream's; open it with "
                             f"simloader.open_store(path), which reads every task's "
                             f"trajectories as one dataset with \"task\" (a StoredMixture)")
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
        """What the store keeps on disk (its first line: bytes per stored step), what the
        stored batches hold (the writer's dataset's `describe()`: which columns of each key
        mean what), and a known fault of the simulator it was written under."""
        said, faulted = self.info["describe"], self.known_fault
        steps = len(self) * steps_and_frames(self)[0]
        size = bytes_on_disk(self.path)
        kept = (f"kept: {len(self)} trajectories of {steps_and_frames(self)[0]} steps in "
                f"{len(self.slots)} committed batch slots, {size / 1e6:,.1f} MB on disk, "
                f"{size / max(steps, 1):,.0f} bytes per step")
        said = said if faulted is None or "known fault" in said else f"{said}\n{faulted}"
        return f"{kept}\n{said}"

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
        return Transitions(self, (state,) if isinstance(state, str) else tuple(state),
                           diverged,
                           (context,) if isinstance(context, str) else tuple(context))

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
        for _, batch in dataset.batches_at(indices, shard):
            pass
        flat_batch = flat(batch)
        row = where["row"]
        out = {}
        for name in self.keys:
            value = flat_batch[name]
            out[name] = value[row] if value.ndim and value.shape[0] == self.nbatch \
                else value.expand(self.nbatch)[row]
        return nested({n: v.detach().cpu().clone() for n, v in out.items()})


def bytes_on_disk(path: str) -> int:
    """The bytes of every file below `path` (links not followed)."""
    total = 0
    for folder, _, files in os.walk(path):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except OSError:  # removed meanwhile (a writer's temporary file)
                pass
    return total
