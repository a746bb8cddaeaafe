"""Splitting one seeded stream across DataLoader workers and torch.distributed ranks.

Every batch has a global index within its rank. Worker `w` of `W` produces the indices
`w, w + W, w + 2W, ...`, which the DataLoader interleaves back into index order, so the stream
a rank sees does not depend on the number of workers (fresh episodes). What each batch draws
from its seed: `seeds.py`; the CPU threads each worker takes: `threads.py`.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Optional

import torch


@dataclasses.dataclass(frozen=True)
class Shard:
    """Where this iterator runs: distributed rank and DataLoader worker, and, for a batch
    split across simulation devices (`sim_device=`), which part of it (`part` of `parts`)."""

    rank: int = 0
    world_size: int = 1
    worker: int = 0
    num_workers: int = 1
    part: int = 0
    parts: int = 1

    def indices(self, num_batches: Optional[int], start: Optional[int] = None):
        """This worker's global batch indices from `start` (endless when num_batches is None)."""
        i = self.worker if start is None else start
        while num_batches is None or i < num_batches:
            yield i
            i += self.num_workers


def distributed_rank() -> Optional[tuple[int, int]]:
    """(rank, world size) from torch.distributed, else torchrun's variables, else None."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        return _environment_rank(os.environ["RANK"], os.environ["WORLD_SIZE"])
    return None


def _environment_rank(rank: str, world: str) -> tuple[int, int]:
    """torchrun's RANK and WORLD_SIZE, checked: a world of at least one rank, a rank in it."""
    def number(name: str, text: str) -> int:
        try:
            return int(text)
        except ValueError:
            raise ValueError(f"{name}: expected an int (the environment variable torchrun "
                             f"sets), got {text!r}") from None
    r, w = number("RANK", rank), number("WORLD_SIZE", world)
    if w < 1:
        raise ValueError(f"WORLD_SIZE: expected an int >= 1 (the number of ranks), got {w}; "
                         f"start the ranks with torchrun, or unset RANK and WORLD_SIZE")
    if not 0 <= r < w:
        raise ValueError(f"RANK: expected an int in [0, WORLD_SIZE={w}), got {r}; start the "
                         f"ranks with torchrun, or unset RANK and WORLD_SIZE")
    return r, w


def current_shard(constructed_rank: Optional[tuple[int, int]] = None) -> Shard:
    """The shard of the calling process.

    DataLoader workers do not inherit the process group, so the rank the dataset saw when it
    was constructed (in the rank's main process) is the fallback there.
    """
    rank, world = distributed_rank() or constructed_rank or (0, 1)
    info = torch.utils.data.get_worker_info()
    worker, nworkers = (info.id, info.num_workers) if info is not None else (0, 1)
    return Shard(rank, world, worker, nworkers)
