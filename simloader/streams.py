"""Which stream each row of a delivered batch belongs to, and which episode of it: what a
buffer fed with live batches needs to join them right.

A stream is the batches of one (rank, DataLoader worker, row). Worker `w` of `W` delivers the
global batch indices `w, w + W, w + 2W, ...`, so with `continue_episodes=True` batch `b`
continues batch `b - W` (not `b - 1`: the DataLoader interleaves the workers' batches), and
gluing batches in arrival order joins unrelated trajectories. Every batch that `SimDataset`
(or `Mixture`) delivers therefore says, per row:

- `"stream"` (nbatch,) int64: the stream's id, `(rank * W + w) * nbatch + row` (a `Mixture`
  makes it `id * ntasks + task`), unique across the ranks, workers and rows of one run;
- `"episode"` (nbatch,) int64: the index, within the stream, of the episode the batch's
  `initial_state` belongs to (0 at the stream's start); frame t's episode is `episode +
  first[:, :t+1].sum(1)` where the batch has `first` (`terminate=`);
- `"initial_first"` (nbatch,) bool: the `initial_state` starts its episode (a stream's first
  batch, every batch without `continue_episodes`, a trajectory restarted after it diverged).

Without `continue_episodes` every batch starts a new episode in every row, so the pair
(stream, episode) names a trajectory either way. `trajectory_ids` packs it into one int64.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional

import torch

from simloader import sharding

STREAM, EPISODE, INITIAL_FIRST = "stream", "episode", "initial_first"
KEYS = (STREAM, EPISODE, INITIAL_FIRST)

# a trajectory id is episode << STREAM_BITS | stream: 2**24 streams (ranks x workers x rows
# x tasks), 2**39 episodes per stream
STREAM_BITS = 24


class StreamTags:
    """The per-row stream keys of one iterator's batches (one DataLoader worker's, or one
    process's), and the counters they carry from batch to batch (in `state_dict`, so that a
    resumed stream goes on counting)."""

    def __init__(self, shard: sharding.Shard, nbatch: int, continuing: bool,
                 saved: Optional[Mapping[str, Any]] = None):
        self.first_id = (shard.rank * shard.num_workers + shard.worker) * nbatch
        self.nbatch, self.continuing = nbatch, continuing
        self.saved = dict(saved) if saved is not None else None
        self.episode: Optional[torch.Tensor] = None  # the next batch's, on its device
        self.fresh: Optional[torch.Tensor] = None

    def tag(self, batch: dict[str, Any]) -> None:
        """Adds the stream keys to `batch` (on its device) and counts on to the next one."""
        device = batch["initial_state"].device
        if self.episode is None:
            saved = self.saved or {"episode": [0] * self.nbatch, "fresh": [True] * self.nbatch}
            self.episode = torch.tensor(saved["episode"], dtype=torch.int64, device=device)
            self.fresh = torch.tensor(saved["fresh"], dtype=torch.bool, device=device)
        batch[STREAM] = torch.arange(self.first_id, self.first_id + self.nbatch,
                                     dtype=torch.int64, device=device)
        batch[EPISODE], batch[INITIAL_FIRST] = self.episode, self.fresh
        last = self.episode
        if "first" in batch:  # episodes begun inside the batch (terminate=)
            last = last + batch["first"].sum(1)
        if self.continuing:  # a diverged trajectory restarts afresh in the next batch
            self.fresh = batch["diverged"].to(torch.bool).clone()
        else:
            self.fresh = torch.ones_like(self.fresh)
        self.episode = last + self.fresh

    def state(self) -> Optional[dict[str, list]]:
        """The counters for the next batch (JSON-serializable), or what was loaded."""
        if self.episode is None:
            return self.saved
        return {"episode": self.episode.tolist(), "fresh": self.fresh.tolist()}


def trajectory_ids(batch: Mapping[str, torch.Tensor], nframes: Optional[int] = None,
                   initial: bool = False) -> torch.Tensor:
    """(nbatch, nframes) int64: the id of the trajectory (episode of a stream) each frame
    belongs to, `episode << STREAM_BITS | stream`, unique across the batches, workers, ranks
    and resets of one run; a continued episode keeps its id from batch to batch. `nframes`:
    the batch's frames, where it has neither `first` nor `state` to count them from.
    `initial`: (nbatch, 1 + nframes), the `initial_state`'s id first."""
    missing = [k for k in KEYS if k not in batch]
    if missing:
        raise KeyError(f"batch: expected the stream keys {list(KEYS)} that SimDataset and "
                       f"Mixture deliver (simloader.streams), it lacks {missing}")
    stream, episode = batch[STREAM], batch[EPISODE]
    if len(stream) and int(stream.max()) >= 1 << STREAM_BITS:
        raise ValueError(f"batch['stream']: ids up to {int(stream.max())}, expected fewer "
                         f"than 2**{STREAM_BITS} streams (ranks x workers x nbatch x tasks) "
                         f"to pack into one trajectory id")
    nframes = _nframes(batch) if nframes is None else nframes
    frames = episode[:, None].expand(-1, nframes)
    if "first" in batch:
        frames = frames + batch["first"].cumsum(1)
    if initial:
        frames = torch.cat([episode[:, None], frames], 1)
    return (frames << STREAM_BITS) | stream[:, None]


def _nframes(batch: Mapping[str, Any]) -> int:
    for key in ("first", "state"):
        if key in batch:
            return int(batch[key].shape[1])
    raise KeyError("batch: no per-frame key to count its frames (expected 'state' or "
                   "'first')")
