"""Transitions `(s_t, a_t, s_t+1)` of a store: a reading pattern (`simloader.store.pattern`)
whose items are the pairs of consecutive frames of one trajectory that are one physics step
(never a frame and the fresh initial state after it).

Which pairs, and in which order, the store's frame table says (`simloader.store.frames`: the
kept trajectories, their `first` frames); the gather is this pattern's own: one `np.take` per
key and batch slot from the memory-mapped shards straight into the batch's tensors (one
storage per dtype, which a DataLoader worker hands over at once), two frames an item, each
key's `s_t` and `s_t+1` contiguous. Through `FramePattern.read` (two reads, `s_t` and
`s_t+1`: the same values) the loader ran at 0.57-0.59M transitions/s against this gather's
0.74-0.79M (2 cores, 2 workers, batches of 4,096 of a 409,600-frame humanoid store).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from simloader.store import shards
from simloader.store.frames import steps_and_frames, transition_indices
from simloader.store.pattern import FramePattern
from simloader.store.shards import StoredArray
from simloader.store.zarr_format import DamagedStore


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


class Transitions(FramePattern):
    """The transitions of a store: item `k` is `{KEY: s_t, "control": a_t, "next/KEY": s_t+1}`
    for every state key, over the trajectories not flagged diverged (by default). With
    `record_every = k` the action is the `k` control rows between two frames
    (`k x ncontrol`). The first frame's predecessor is the initial state for the
    key `"state"` (`initial_state`), so a trajectory gives `nframes` transitions; other keys
    have no stored initial value and give `nframes - 1`. Each `context` key (a per-trajectory
    value: `params/...`, ...) is in every item too, its trajectory's value. In a store of
    episodes that end (`terminate=`: a stored `first`), a frame is never paired with the
    fresh initial state that follows it: the transitions into a `first` frame are left out.
    Transitions are ordered by batch slot, then trajectory, then frame.
    """

    def __init__(self, stored: Any, keys: tuple[str, ...], diverged: str,
                 context: tuple[str, ...] = ()):
        super().__init__(stored, keys, diverged, context, "produced")
        nstep, self.nframes = steps_and_frames(stored)
        # every index `gather` takes is then in range: frames of `nframes`, controls of nstep
        if stored.metas["control"]["shape"][1] != nstep:
            raise DamagedStore(f"{stored.layouts['control'].file}: shape "
                               f"{stored.metas['control']['shape']}, expected {nstep} control "
                               f"rows per trajectory (nstep in the store's root)")
        self.first = 0 if self.initial else 1  # frame 0's predecessor is stored
        self.per = self.nframes - self.first

    @functools.cached_property
    def targets(self) -> np.ndarray:
        """Each transition's target (its `s_t+1`) as a position of the frame table: every
        stored frame that is no fresh start and whose predecessor is in its own trajectory
        (its frame before, or for `state` its initial state), in slot order (`slot_order`).
        Made at the first use (the table reads the flags and `first` marks of every slot)."""
        table = self.table
        positions = np.flatnonzero(~table.first & (table.frame >= self.first))
        order = self.slot_order(positions)
        return positions if order is None else positions[order]

    def locate(self, ks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(stored trajectory, target frame) of transitions `ks` (in range)."""
        at = self.targets[ks]
        return self.table.trajectory[at], self.table.frame[at].astype(np.int64)

    def __len__(self) -> int:
        return len(self.targets)

    @property
    def block(self) -> int:
        """The transitions of one batch slot (where none were dropped), which a
        quasi-random order reads as a block (one shard per array)."""
        return self.stored.nbatch * self.per

    def read_ahead(self, blocks: np.ndarray, block: int) -> None:
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

