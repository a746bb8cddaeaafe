"""The orders an epoch reads a store in, as batch samplers (lists of indices per batch).

`"quasi_random"` (FFCV's answer to datasets bigger than memory): the indices are cut into
blocks of consecutive items (a block is about one batch slot: one shard file per array), the
blocks are shuffled, and `window` blocks at a time are read and their items shuffled
together. Each shard file is then read once per epoch, whole and in order, so an epoch runs
at the disk's sequential speed; batches mix `window` random places of the store. `"random"`
is a full permutation (every batch from everywhere: one small read per item on a store the
page cache cannot hold); `"sequential"` is the stored order.

`mean_jump` measures how random an order is: the mean distance between consecutive indices
of the epoch's order, which is about n/3 for a uniform permutation of n and 1 for the stored
order. (Each batch is handed over sorted: a batch is a set, and sorted it is read in the
files' order.)

A `BlockOrder` resumes: `state_dict()` says where the latest epoch stands (its number, the
batches handed out, the seed) and `load_state_dict()` makes the next `iter()` hand out the rest
of that epoch, then the epochs after it, as an uninterrupted sampler would (torchdata's
`StatefulDataLoader` saves and loads it with the loader's state).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, Optional

import numpy as np
import torch

ORDERS = ("quasi_random", "random", "sequential")


def pattern_loader(view: Any, n: int, batch_size: int, order: str, block: int,
                   window: Optional[int], drop_last: bool, seed: Optional[int], arrays: int,
                   kwargs: dict, ahead: Optional[Callable[[np.ndarray, int], None]] = None
                   ) -> torch.utils.data.DataLoader:
    """The loader every reading pattern (transitions, windows) hands out: a `BlockOrder` of
    its `n` items in blocks of `block` (one batch slot's), `window` blocks shuffled together
    (default: as many as the open-shard table holds for `arrays` arrays read per block),
    over a copy of `view` that reads whole shards in block orders; each batch one
    `view.gather` (no per-item tensors, no collation), resumable
    (`simloader.loaders.StatefulDataLoader`)."""
    from simloader.loaders import StatefulDataLoader
    from simloader.store.shards import MAX_OPEN
    sampler = BlockOrder(n, batch_size, order, block,
                         window or max(1, MAX_OPEN // (2 * arrays)), drop_last, seed,
                         ahead=ahead)
    copy = object.__new__(type(view))
    copy.__dict__.update(view.__dict__)
    copy.will_need = order != "random"  # a block is read whole, a random item alone
    return StatefulDataLoader(copy, batch_size=None, sampler=sampler, **kwargs)


class BlockOrder(torch.utils.data.Sampler):
    """Batches of `batch_size` indices of `range(n)` in one of `ORDERS`, each batch's indices
    in increasing order; a new order each epoch, drawn from `seed` and the epoch's number
    (reproducible, as a seeded sampler). Each `iter()` starts the next epoch (or the rest of
    the one `load_state_dict` names)."""

    # what must be equal for a saved position to mean the same batches
    _SHAPE = ("n", "batch_size", "order", "block", "window", "drop_last")

    def __init__(self, n: int, batch_size: int, order: str = "quasi_random", block: int = 1,
                 window: int = 8, drop_last: bool = False, seed: Optional[int] = None,
                 ahead: Optional[Callable[[np.ndarray, int], None]] = None):
        if order not in ORDERS:
            raise ValueError(f"order: expected one of {ORDERS}, got {order!r}")
        if not isinstance(batch_size, int) or isinstance(batch_size, bool) or batch_size < 1:
            raise ValueError(f"batch_size: expected a positive int, got {batch_size!r}")
        if not isinstance(window, int) or isinstance(window, bool) or window < 1:
            raise ValueError(f"window: expected a positive int (blocks shuffled together), "
                             f"got {window!r}")
        self.n, self.batch_size, self.order = n, batch_size, order
        self.block, self.window, self.drop_last = max(1, int(block)), window, drop_last
        self.seed = int(torch.empty((), dtype=torch.int64).random_().item()) \
            if seed is None else seed
        self.epoch = 0  # the epoch the next iter() reads
        self._resume = 0  # the batch of it the next iter() starts at (load_state_dict)
        self._progress: Optional[list[int]] = None  # latest iter(): [epoch, batches out]
        self.ahead = ahead  # ahead(first indices of a window's blocks, block): read them soon

    def __len__(self) -> int:
        return self.n // self.batch_size if self.drop_last else -(-self.n // self.batch_size)

    def indices(self, epoch: int) -> np.ndarray:
        """Every index once, in this epoch's order."""
        return self._plan(epoch)[0]

    def _plan(self, epoch: int) -> tuple[np.ndarray, list[tuple[int, np.ndarray]]]:
        """This epoch's order, and for "quasi_random" its windows: (position of the window's
        first index in the order, the first indices of its blocks)."""
        if self.order == "sequential":
            return np.arange(self.n), []
        rng = np.random.default_rng([self.seed, epoch])
        if self.order == "random":
            return rng.permutation(self.n), []
        starts = rng.permutation(np.arange(0, self.n, self.block))
        out = np.empty(self.n, dtype=np.int64)
        windows = []
        filled = 0
        for w in range(0, len(starts), self.window):
            blocks = starts[w:w + self.window]
            window = np.concatenate([np.arange(s, min(s + self.block, self.n)) for s in blocks])
            out[filled:filled + len(window)] = rng.permutation(window)
            windows.append((filled, blocks))
            filled += len(window)
        return out, windows

    def state_dict(self) -> dict[str, Any]:
        """Where the latest epoch stands: its number and the batches handed out of it (or,
        before any `iter()`, where the next one starts), the seed, and the shape of the
        order (checked when loaded). Small and JSON-serializable."""
        epoch, position = self._progress or (self.epoch, self._resume)
        return {"epoch": epoch, "position": position, "seed": self.seed,
                **{k: getattr(self, k) for k in self._SHAPE}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """The next `iter()` hands out the batches of `state`'s epoch after its position, in
        the same order (the saved seed is taken); the one after it, the next epoch. A state
        taken at the end of an epoch resumes an empty rest of it, as the loader it was saved
        with: `StatefulDataLoader` knows the epoch was over and starts the next.

        Raises:
          ValueError: `state` is of another order (another store, batch size, order, ...).
        """
        if not isinstance(state, dict) or not {"epoch", "position", "seed", *self._SHAPE} \
                <= set(state):
            raise ValueError(f"state: expected a BlockOrder.state_dict(), got {state!r}")
        differ = [f"{k}: saved {state[k]!r}, now {getattr(self, k)!r}" for k in self._SHAPE
                  if state[k] != getattr(self, k)]
        if differ:
            raise ValueError(f"state: saved by another order of batches ({'; '.join(differ)}): "
                             f"the saved position would not mean the same batches")
        self.seed, self.epoch, self._resume = int(state["seed"]), int(state["epoch"]), \
            int(state["position"])
        self._progress = None

    def __iter__(self) -> Iterator[np.ndarray]:
        # the epoch is taken when the iterator is made, not at its first batch: a loader may
        # make one and drop it unstarted (StatefulDataLoader does when it resumes), and the
        # next must read the next epoch, not this one again
        epoch, start = self.epoch, self._resume
        self.epoch, self._resume = epoch + 1, 0
        progress = self._progress = [epoch, start]
        return self._batches(epoch, start, progress)

    def _batches(self, epoch: int, start: int, progress: list[int]) -> Iterator[np.ndarray]:
        order, windows = self._plan(epoch)
        stop = min(len(self) * self.batch_size, self.n)
        first = start * self.batch_size
        # the reads of a window overlap the work on the one before: when window k begins,
        # window k + 1 is announced (`ahead`, in the process that samples); a resumed epoch
        # starts at the window it stopped in
        announced = max(0, int(np.searchsorted([w[0] for w in windows], first, "right")) - 1)
        for begin in range(first, stop, self.batch_size):
            while self.ahead is not None and announced < len(windows) and \
                    (announced == 0 or windows[announced - 1][0] <= begin):
                self.ahead(windows[announced][1], self.block)
                announced += 1
            progress[1] += 1  # counted as it is handed out: a state taken after it has it
            # a batch is a random set: handed over in increasing order, it is read in the
            # files' order (and `Transitions.gather` needs no reordering); as an array, which
            # crosses to a DataLoader worker faster than a list (0.34M -> 0.43M humanoid
            # transitions/s at batches of 1024 with 2 workers)
            yield np.sort(order[begin:begin + self.batch_size])


def mean_jump(sampler: BlockOrder, epoch: int = 0) -> float:
    """The mean |difference| of consecutive indices of an epoch's order (n/3 for uniform)."""
    indices = sampler.indices(epoch)
    return float(np.abs(np.diff(indices)).mean()) if len(indices) > 1 else 0.0
