"""A store's frames as streams: what windows and episodes are cut from.

A stored trajectory is `nframes` frames; its `initial_state` is the frame before them (frame
-1 here), the trajectory's first frame (`first=True`), where every asked per-frame key has an
initial value (the state; cameras render from it). A store written with
`continue_episodes=True` holds streams: the batches of one (rank, DataLoader worker, row),
where worker w of W wrote batches w, w + W, w + 2W, ... and each one's trajectory continues
the one before it; those are joined here in order, the first one's initial state leading. A
stream is cut where a batch of it is missing (not committed yet) or left out (flagged
diverged, under `diverged="drop"`): what follows starts afresh, its batch's initial state a
`first` frame.

`FrameTable` lays every stream's frames end to end: flat position p is frame `frame[p]` of
stored trajectory `trajectory[p]`; `first[p]` marks a fresh start (a segment's first frame, or
a stored `first` frame: the fresh initial state after a reset), so an episode runs from a
`first` frame to the next one or to its segment's end. Windows and episodes are ranges of
positions that never span two segments; `read` fetches any positions' values, one shard
read per key and batch slot.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np

from simloader.layout import did_you_mean
from simloader.store.zarr_format import DamagedStore

INITIAL = -1  # the frame index of a trajectory's initial state


def item_index(i: Any, n: int) -> int:
    """Item `i` of `n` (negative counts from the end), or the TypeError / IndexError a
    sequence raises, naming the dataset."""
    if isinstance(i, bool) or not isinstance(i, (int, np.integer)):
        raise TypeError(f"StoredDataset: index must be an int, got {type(i).__name__}")
    if not -n <= i < n:
        raise IndexError(f"StoredDataset: index {i} out of range for {n} trajectories")
    return int(i) % n


def transition_indices(ks: Any, n: int) -> np.ndarray:
    """Transitions `ks` of `n` as int64 indices in range (negative counts from the end), or
    the IndexError naming the first out of range."""
    ks = np.asarray(ks, dtype=np.int64).reshape(-1)
    if len(ks) and (ks.min() < -n or ks.max() >= n):
        bad = int(ks[(ks < -n) | (ks >= n)][0])
        raise IndexError(f"Transitions: index {bad} out of range for {n} transitions")
    return ks % max(n, 1)


# batch keys with one value per trajectory (and no frame axis, whatever their width)
PER_TRAJECTORY = ("initial_state", "diverged", "overflow", "policy/version")
PER_TRAJECTORY_GROUPS = ("params/", "provenance/")


def steps_and_frames(stored: Any) -> tuple[int, int]:
    """(nstep, nframes) of the store, from its root."""
    nstep, every = stored.info.get("nstep"), int(stored.info["record_every"])
    if not isinstance(nstep, int) or isinstance(nstep, bool) or nstep < 1 or nstep % every:
        raise DamagedStore(f"{stored.folder.where('zarr.json')}: the attribute "
                           f"simloader.nstep is {nstep!r}, expected a positive multiple of "
                           f"record_every={every}")
    return nstep, nstep // every


def key_kinds(stored: Any) -> tuple[list[str], list[str]]:
    """(per-frame keys, per-trajectory keys) of a store. Per frame: arrays
    `ntrajectories x nframes x ...` (`nframes = nstep // record_every`, from the store's
    root) of a recorded or policy key. Per trajectory: the keys of `PER_TRAJECTORY` and
    `PER_TRAJECTORY_GROUPS` (`initial_state` is `ntrajectories x nstate`, which may equal
    `nframes`), and every array without a time axis. `control` is neither: it is every
    transition's action."""
    nstep, nframes = steps_and_frames(stored)
    frames, constants = [], []
    for name, meta in stored.metas.items():
        shape = meta["shape"]
        if name in PER_TRAJECTORY or name.startswith(PER_TRAJECTORY_GROUPS) or \
                len(shape) < 2 or shape[1] not in (nstep, nframes):
            constants.append(name)
        elif shape[1] == nframes and name != "control":
            frames.append(name)
    return sorted(frames), sorted(constants)

def checked_keys(stored: Any, keys: Sequence[str], context: Sequence[str]) -> tuple[str, ...]:
    """Checks the per-frame `keys` a reading pattern pairs or windows (`state=`) and returns
    the per-trajectory keys `context` names (`"params"` stands for all of `params/`), or the
    KeyError naming the key, what it is and what the store has."""
    per_frame, per_trajectory = key_kinds(stored)
    for key in keys:
        if key in per_frame:
            continue
        if key in per_trajectory:
            raise KeyError(f"state: {key!r} is per-trajectory (one value per trajectory, "
                           f"no frame axis); pass it as context=({key!r},) to have it "
                           f"with each transition or window; per-frame keys: {per_frame}")
        if key == "control":
            raise KeyError(f"state: 'control' is every transition's action already; "
                           f"per-frame keys: {per_frame}")
        raise KeyError(f"state: expected a per-frame key of the store (shape "
                       f"ntrajectories x nframes x ...), got {key!r}"
                       f"{did_you_mean(key, per_frame)}; per-frame keys: {per_frame}")
    constants = []
    for key in context:
        found = [n for n in per_trajectory if n == key or n.startswith(key + "/")]
        if not found:
            where = "is per-frame: pass it in state=" if key in per_frame else \
                f"is not a per-trajectory key of the store{did_you_mean(key, per_trajectory)}"
            raise KeyError(f"context: {key!r} {where}; per-trajectory keys: "
                           f"{per_trajectory}")
        constants += [n for n in found if n not in constants]
    return tuple(constants)


@dataclasses.dataclass
class FrameTable:
    """Every frame of the store's kept streams, end to end (see the module's docstring). Per
    position only what cannot be derived (13 bytes a frame); where episodes and segments end
    is found from their starts."""

    trajectory: np.ndarray  # (F,) int64: the stored trajectory of each position
    frame: np.ndarray  # (F,) int32: its frame in that trajectory (INITIAL: its initial state)
    first: np.ndarray  # (F,) bool: a fresh start (every segment's first position is one)
    segment_starts: np.ndarray  # (S,) int64, ascending: each segment's first position

    def __len__(self) -> int:
        return len(self.trajectory)

    @functools.cached_property
    def _firsts(self) -> np.ndarray:
        return np.flatnonzero(self.first)

    def episode_end(self, positions: np.ndarray) -> np.ndarray:
        """One past the last position of each position's episode: the next fresh start (a
        segment's end is one too), or the table's end."""
        firsts = self._firsts
        return np.r_[firsts, len(self)][np.searchsorted(firsts, positions, side="right")]

    def episodes(self) -> tuple[np.ndarray, np.ndarray]:
        """(first position, one past the last) of every episode, in order."""
        starts = self._firsts
        return starts, np.r_[starts[1:], len(self)].astype(np.int64)

    def segments(self) -> tuple[np.ndarray, np.ndarray]:
        """(first position, one past the last) of every segment (a stream, or a part of one
        between missing or left-out batches), in order."""
        starts = self.segment_starts
        return starts, np.r_[starts[1:], len(self)].astype(np.int64)


def build(stored: Any, kept: np.ndarray, initial: bool) -> FrameTable:
    """The frame table of `stored`'s trajectories `kept` (ascending stored indices), with
    each segment's leading initial state where `initial`."""
    nframes = steps_and_frames(stored)[1]
    order, starts = _chains(stored, kept)  # trajectories in stream order, chain starts
    n = len(order)
    lead = starts & initial  # a chain's first trajectory leads with its initial state
    per = nframes + lead.astype(np.int64)
    total = int(per.sum())
    offsets = np.r_[0, np.cumsum(per)[:-1]].astype(np.int64)
    trajectory = np.repeat(order, per)
    within = np.arange(total, dtype=np.int64) - np.repeat(offsets, per)
    frame = (within - np.repeat(lead.astype(np.int64), per)).astype(np.int32)
    del within
    first = np.zeros(total, dtype=bool)
    segment_starts = offsets[starts]
    first[segment_starts] = True  # a segment's first frame, initial or not
    stored_first = _stored_first(stored, order)
    if stored_first is not None:
        kept_frames = frame >= 0
        first[kept_frames] |= stored_first[np.repeat(np.arange(n), per)[kept_frames],
                                           frame[kept_frames]]
    return FrameTable(trajectory, frame, first, segment_starts)


def _chains(stored: Any, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The kept trajectories in stream order, and where a chain (a segment) starts: every
    trajectory of a store of independent batches; in a continued store, where a stream
    begins, a batch before it is missing or left out, or the one before it diverged."""
    kept = np.asarray(kept, dtype=np.int64)
    fingerprint = stored.info.get("fingerprint") or {}
    if not fingerprint.get("continue_episodes") or not len(kept):
        return kept, np.ones(len(kept), dtype=bool)
    arrays = stored.arrays()
    nbatch = stored.nbatch
    columns = {}
    for name in ("rank", "batch", "row", "num_workers"):
        # copied out slot by slot: a view would keep each slot's map (and its descriptor)
        # open past the bounded table of open shards
        values = np.empty(len(stored.slots) * nbatch, dtype=np.int64)
        for k, slot in enumerate(stored.slots):
            values[k * nbatch:(k + 1) * nbatch] = arrays["provenance/" + name].slot(int(slot))
        columns[name] = values[kept]
    workers = np.maximum(columns["num_workers"], 1)
    worker = columns["batch"] % workers
    # stream order: (rank, worker, row), then the batch index
    order = np.lexsort((columns["batch"], columns["row"], worker, columns["rank"]))
    rank, wk, row, batch = (columns["rank"][order], worker[order], columns["row"][order],
                            columns["batch"][order])
    same_stream = np.r_[False, (rank[1:] == rank[:-1]) & (wk[1:] == wk[:-1]) &
                        (row[1:] == row[:-1])]
    follows = np.r_[False, batch[1:] == batch[:-1] + workers[order][1:]]
    # a trajectory flagged diverged (kept under diverged="keep") is not continued: the
    # engine restarts its row from a fresh initial state in the next batch
    flagged = stored.flagged()[kept[order]]
    follows[1:] &= ~flagged[:-1]
    return kept[order], ~(same_stream & follows)


def _stored_first(stored: Any, order: np.ndarray) -> Any:
    """The stored `first` flags (n, nframes) of trajectories `order`, or None in a store
    without episodes."""
    if "first" not in stored.layouts:
        return None
    first = stored.arrays()["first"]
    nbatch = stored.nbatch
    slots = stored.slots[order // nbatch]
    out = np.empty((len(order), first.trailing[0]), dtype=bool)
    for slot, at in group_by_slot(slots):
        out[at] = first.slot(slot)[order[at] % nbatch]
    return out


def group_by_slot(slots: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(slot, the positions of `slots` holding it) for each slot, each read once."""
    order = np.argsort(slots, kind="stable")
    sorted_slots = slots[order]
    bounds = np.flatnonzero(sorted_slots[1:] != sorted_slots[:-1]) + 1
    return [(int(sorted_slots[a]), order[a:b]) for a, b in
            zip(np.r_[0, bounds], np.r_[bounds, len(order)]) if b > a]


def read(stored: Any, table: FrameTable, positions: np.ndarray, keys: Sequence[str],
         context: Sequence[str], every: int, will_need: bool = False) -> dict[str, np.ndarray]:
    """The values at `positions` (any shape; flat positions of `table`): each per-frame key
    `(*shape, ...)` (a trajectory's initial state for `state` at an INITIAL frame), `control`
    the rows that produced each frame (`every x ncontrol` with `record_every > 1`; NaN at a
    `first` frame: nothing produced it), `first`, `terminated`, `truncated` (always there:
    False where the store has no episodes, and at initial frames), and each `context` key
    its trajectory's value."""
    shape = positions.shape
    flat_positions = positions.reshape(-1)
    trajectory = table.trajectory[flat_positions]
    frame = table.frame[flat_positions]
    nbatch = stored.nbatch
    slots = stored.slots[trajectory // nbatch]
    rows = trajectory % nbatch
    arrays = stored.arrays()
    n = len(flat_positions)
    out: dict[str, np.ndarray] = {}
    for key in keys:
        out[key] = np.empty((n, *arrays[key].trailing[1:]), dtype=arrays[key].dtype)
    control = arrays["control"]
    width = control.trailing[1:]
    out["control"] = np.empty((n, *((every,) if every > 1 else ()), *width),
                              dtype=control.dtype)
    # False where the store has no episodes (the keys are there either way)
    flags = [k for k in ("terminated", "truncated") if k in arrays]
    for key in ("terminated", "truncated"):
        out[key] = np.zeros(n, dtype=bool)
    for key in context:
        out[key] = np.empty((n, *arrays[key].trailing), dtype=arrays[key].dtype)
    steps = np.arange(every)
    for slot, at in group_by_slot(slots):
        r, f = rows[at], frame[at]
        stored_frames = f >= 0
        s_at, i_at = at[stored_frames], at[~stored_frames]
        for key in keys:
            if not out[key].size:
                continue  # a key without values (sensordata of a model without sensors)
            seq = arrays[key].slot(slot, will_need)  # nbatch x nframes x ...
            flat = seq.reshape(seq.shape[0] * seq.shape[1], -1)
            out[key].reshape(n, -1)[s_at] = flat[r[stored_frames] * seq.shape[1] +
                                                 f[stored_frames]]
            if len(i_at):  # only `state` has one (the caller asks for no other then)
                initial = arrays["initial_state"].slot(slot, will_need)
                out[key].reshape(n, -1)[i_at] = initial[r[~stored_frames]]
        rows_of = control.slot(slot, will_need)  # nbatch x nstep x ncontrol
        flat = rows_of.reshape(rows_of.shape[0] * rows_of.shape[1], -1)
        taken = flat[((r[stored_frames] * rows_of.shape[1] + f[stored_frames] * every)
                      [:, None] + steps).reshape(-1)]
        out["control"].reshape(n, -1)[s_at] = taken.reshape(len(s_at), -1)
        for key in flags:
            seq = arrays[key].slot(slot, will_need)
            out[key][s_at] = seq[r[stored_frames], f[stored_frames]]
        for key in context:
            if out[key].size:
                seq = arrays[key].slot(slot, will_need)
                out[key].reshape(n, -1)[at] = seq.reshape(seq.shape[0], -1)[r]
    first = table.first[flat_positions]
    out["first"] = first
    if out["control"].dtype.kind == "f":
        out["control"][first] = np.nan  # nothing produced a fresh frame
    return {k: v.reshape(*shape, *v.shape[1:]) for k, v in out.items()}
