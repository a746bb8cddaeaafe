"""Windows of T consecutive frames, and whole episodes: what world models train and are
evaluated on, cut from a store's streams (`simloader.store.frames`).

The conventions a world model trains in, by name:

| | `ends=` | `actions=` |
| --- | --- | --- |
| DreamerV3 | `"cross"`: windows run across an episode end, the fresh frame `first=True` (`is_first`: the model resets its latent there) | `"next"`: the action taken after frame t |
| TD-MPC2, torchrl `SliceSampler(strict_length=True)` | `"inside"`: every window inside one episode; episodes shorter than the window are never sampled | `"produced"`: the action that produced frame t (NaN at a `first` frame) |
| LeRobot, DIAMOND, IRIS | `"pad"`: windows start anywhere inside an episode and are padded past its end, `mask` False there (`_is_pad`) | `"next"` |

Under `actions="next"` the last frame of an episode (a frame that ended it, or the last one
stored) has no action after it: its row is zeros (a padded frame's too).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np
import torch

from simloader.store import frames as stream_frames
from simloader.store.pattern import FramePattern

ENDS = ("cross", "inside", "pad")


class Windows(FramePattern):
    """Every window of `length` consecutive frames of a store (`StoredDataset.windows`): item
    `i` is a dict of tensors, `gather(indices)` a batch `(B, length, ...)`: the per-frame
    keys asked, `control` (see `actions`), `first`, `terminated`, `truncated` (False where
    the store has no episodes), `mask` under `ends="pad"`, each `context` key `(B, ...)` (the window's
    first frame's trajectory's), and the cameras of `StoredDataset(cameras=)` rendered for
    the window's frames only. Windows never span two streams; a stream's frames are every
    trajectory's initial state (`first=True`) and its stored frames, and a continued store's
    batches joined (`simloader.store.frames`). The conventions are the module's table."""

    frame_axes = 1  # a batch's keys are (B, length, ...), context keys aside

    def __init__(self, stored: Any, length: int, keys: tuple[str, ...], ends: str,
                 actions: str, diverged: str, context: tuple[str, ...]):
        if isinstance(length, bool) or not isinstance(length, (int, np.integer)) or length < 1:
            raise ValueError(f"length: expected a positive int (frames per window), got "
                             f"{length!r}")
        if ends not in ENDS:
            raise ValueError(f"ends: expected one of {ENDS}, got {ends!r}")
        super().__init__(stored, keys, diverged, context, actions)
        self.length, self.ends = int(length), ends

    @functools.cached_property
    def _starts(self) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Each window's first position, and under "pad" one past its episode's end; in the
        store's slot order (`slot_order`)."""
        table, length = self.table, self.length
        if self.ends == "cross":
            first, end = table.segments()
        else:
            first, end = table.episodes()
        room = end - first if self.ends == "pad" else np.maximum(end - first - length + 1, 0)
        offsets = np.r_[0, np.cumsum(room)[:-1]].astype(np.int64)
        starts = np.repeat(first, room) + (np.arange(int(room.sum())) - np.repeat(offsets, room))
        limits = np.repeat(end, room) if self.ends == "pad" else None
        order = self.slot_order(starts)
        if order is not None:
            starts = starts[order]
            limits = None if limits is None else limits[order]
        return starts.astype(np.int64), limits

    def __len__(self) -> int:
        return len(self._starts[0])

    def gather(self, indices: Sequence[int]) -> dict[str, torch.Tensor]:
        """The windows `indices` (negative counts from the end) as a batch `(B, length, ...)`."""
        ks = stream_frames.transition_indices(indices, len(self))
        starts, limits = self._starts
        positions = starts[ks][:, None] + np.arange(self.length)
        return self.read(positions, None if limits is None else limits[ks])


class Episodes(FramePattern):
    """Whole episodes of a store (`StoredDataset.episodes`): item `i` is episode `i` (from a
    `first` frame to the frame before the next one, or to its stream's end) as a dict of
    tensors `(length, ...)`, with the keys a window has (`control` as `actions` says; each
    `context` key its value)."""

    def __len__(self) -> int:
        return len(self.table.episodes()[0])

    def __getitem__(self, i: Any) -> dict[str, torch.Tensor]:
        i = stream_frames.item_index(i, len(self))
        first, end = self.table.episodes()
        positions = np.arange(first[i], end[i])[None]
        return {k: v[0] for k, v in self.read(positions).items()}

    def lengths(self) -> np.ndarray:
        """Every episode's number of frames."""
        first, end = self.table.episodes()
        return end - first
