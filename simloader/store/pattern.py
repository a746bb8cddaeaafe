"""What every reading pattern of a store shares (`Transitions`, `Windows`, `Episodes`): the
store's frame table over the kept trajectories (`simloader.store.frames`), the keys checked,
`read` of any positions (tensors; cameras rendered for exactly those frames), a batch's items
as views of one gather, and the loader (`simloader.store.order`). A pattern says only which
positions make an item: a new pattern is one file beside these.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, Callable, Optional

import numpy as np
import torch

from simloader.store import frames as stream_frames
from simloader.store import order as orders
from simloader.store.frames import FrameTable

ACTIONS = ("produced", "next")


class FramePattern(torch.utils.data.Dataset):
    """What windows and episodes share: the store's frame table over the kept trajectories,
    the keys checked, and `read` of any positions (tensors, cameras rendered for exactly
    those frames)."""

    def __init__(self, stored: Any, keys: tuple[str, ...], diverged: str,
                 context: tuple[str, ...], actions: str):
        if diverged not in ("drop", "keep"):
            raise ValueError(f"diverged: expected 'drop' or 'keep', got {diverged!r}")
        if actions not in ACTIONS:
            raise ValueError(f"actions: expected one of {ACTIONS}, got {actions!r}")
        if not len(stored.slots):
            raise ValueError(
                f"{type(self).__name__.lower()}: the store at {stored.path!r} has no committed "
                f"batch slot yet (none of its {stored.info['batches']} slot(s) is marked "
                f"written: its writer was stopped before its first batch was complete, or the "
                f"marks were removed); there is nothing to read. Calling simloader.write with "
                f"the same dataset writes it")
        self.stored, self.keys, self.actions = stored, keys, actions
        self.context = stream_frames.checked_keys(stored, keys, context)
        self.drop_flagged = diverged == "drop"
        self.every = int(stored.info["record_every"])
        self.will_need = False  # read whole shards (set by `loader` for block orders)
        # a trajectory's initial state leads it where every key asked has one
        self.initial = keys == ("state",)

    # (blocks, block) -> None: the shard files of the blocks of items starting at `blocks`,
    # read into the page cache in the background (`order.BlockOrder`); None: none read ahead
    read_ahead: Optional[Callable[[np.ndarray, int], None]] = None

    @functools.cached_property
    def table(self) -> FrameTable:
        """The frames of the kept streams, made at the first use (it reads the flags, the
        provenance and the `first` marks of every slot)."""
        kept = (np.flatnonzero(~self.stored.flagged()) if self.drop_flagged else
                np.arange(len(self.stored)))
        return stream_frames.build(self.stored, kept, initial=self.initial)

    def slot_order(self, positions: np.ndarray) -> Optional[np.ndarray]:
        """The stable order that lays `positions` out by the batch slot of their trajectory,
        or None where they are so already. A continued stream runs across slots: in stream
        order the items of one block of a quasi-random epoch would read a slot each, and the
        table of open shards would thrash."""
        slots = self.table.trajectory[positions] // self.stored.nbatch
        if not len(slots) or (slots[1:] >= slots[:-1]).all():
            return None
        return np.argsort(slots, kind="stable")

    def read(self, positions: np.ndarray, limit: Optional[np.ndarray] = None
             ) -> dict[str, torch.Tensor]:
        """The frames at `positions` (B, L) as tensors (B, L, ...); `limit` (B,): one past
        the last real position of each row (padding after it: zeros, flags False, `mask`)."""
        table = self.table
        real = None
        if limit is not None:
            real = positions < limit[:, None]
            positions = np.where(real, positions, (limit - 1)[:, None])
        out = stream_frames.read(self.stored, table, positions, self.keys, self.context,
                                 self.every, self.will_need)
        if self.actions == "next":
            after = positions + 1
            inside = after < table.episode_end(positions)
            if real is not None:
                inside &= np.r_[real[:, 1:].T, np.zeros((1, len(real)), bool)].T
            following = stream_frames.read(self.stored, table, np.where(inside, after,
                                                                         positions),
                                           (), (), self.every, self.will_need)["control"]
            following[~inside] = 0
            out["control"] = following
        for key in self.context:  # one value per window: its first frame's trajectory's
            out[key] = out[key][:, 0]
        if real is not None:
            for key, value in out.items():
                if key not in self.context:
                    value[~real] = 0
            out["mask"] = real
        tensors = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}
        cameras = self.stored.cameras
        if cameras is not None:
            states = out["state"] if "state" in out else stream_frames.read(
                self.stored, table, positions, ("state",), (), self.every)["state"]
            b, length = positions.shape
            trajectories = table.trajectory[positions.reshape(-1)]
            for key, images in cameras.frames(states.reshape(b * length, 1, -1),
                                              trajectories).items():
                images = images.reshape(b, length, *images.shape[2:])
                if real is not None:
                    images[torch.from_numpy(~real)] = 0
                tensors[key] = images
        return tensors

    def __getitem__(self, k: Any) -> dict[str, torch.Tensor]:
        """Item `k` (negative counts from the end; `IndexError` past it, which ends
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

    def gather(self, ks: Sequence[int]) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    @property
    def block(self) -> int:
        """The items of one batch slot, about, which a quasi-random order reads as a block
        (one shard per array)."""
        return max(1, len(self) // max(1, len(self.stored.slots)))

    def loader(self, batch_size: int, order: str = "quasi_random", drop_last: bool = False,
               window: Optional[int] = None, seed: Optional[int] = None,
               shuffle: Optional[bool] = None, **kwargs: Any) -> torch.utils.data.DataLoader:
        """A DataLoader of batches of `batch_size` items, each read with one gather per key
        and batch slot (a batch sampler hands the dataset all of a batch's indices,
        `batch_size=None`: no per-item tensors are made or collated).

        Each iteration is one epoch, in a new order drawn from `seed` and the epoch's number.
        With torchdata installed the loader is its `StatefulDataLoader`, which resumes:
        `loader.state_dict()` taken after any batch, loaded into a loader made the same way
        (`load_state_dict`, even in a new process, with `num_workers` as it was: a state of
        another `num_workers` is refused by name), makes the next iteration deliver exactly
        the rest of that epoch, bit for bit, and the iterations after it the epochs that
        follow (the order's seed is in the state, so `seed=None` resumes too). The order's
        own state is `loader.sampler.state_dict()` (a `simloader.store.order.BlockOrder`:
        the epoch, the batches handed out of it, the seed). Without torchdata it is a plain
        `torch.utils.data.DataLoader`, which does not resume.

        Args:
          order: `"quasi_random"` (default: blocks of one batch slot's items in shuffled
            order, `window` blocks shuffled together; an epoch over a store bigger than
            memory reads each shard once, whole: see `simloader.store.order`), `"random"`
            (a full permutation) or `"sequential"`.
          window: blocks shuffled together (default: as many as the open-shard table holds).
          seed: the orders' seed (default: drawn from torch's generator, as `shuffle=True`).
          shuffle: the older spelling: True is `order="random"`, False `"sequential"`.
          kwargs: to the DataLoader (`num_workers=`, ...).
        """
        if shuffle is not None:
            order = "random" if shuffle else "sequential"
        return orders.pattern_loader(self, len(self), batch_size, order, self.block, window,
                                     drop_last, seed, len(self.keys) + 2, kwargs,
                                     ahead=self.read_ahead)
