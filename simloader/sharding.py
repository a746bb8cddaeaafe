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
        return int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    return None


def current_shard(constructed_rank: Optional[tuple[int, int]] = None) -> Shard:
    """The shard of the calling process.

    DataLoader workers do not inherit the process group, so the rank the dataset saw when it
    was constructed (in the rank's main process) is the fallback there.
    """
    rank, world = distributed_rank() or constructed_rank or (0, 1)
    info = torch.utils.data.get_worker_info()
    worker, nworkers = (info.id, info.num_workers) if info is not None else (0, 1)
    return Shard(rank, world, worker, nworkers)
