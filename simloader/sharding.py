"""Splitting one seeded stream across DataLoader workers and torch.distributed ranks.

Every batch has a global index within its rank. Worker `w` of `W` produces the indices
`w, w + W, w + 2W, ...`, which the DataLoader interleaves back into index order, so the stream
a rank sees does not depend on the number of workers (fresh episodes). All randomness of batch
`i` on rank `r` comes from `SeedSequence(seed, spawn_key=(r, i, purpose))`: streams of different
batches, workers and ranks never coincide, and the same seed repeats the whole stream. A batch
split across several simulation devices (`sim_device=`) draws each part `p` from
`spawn_key=(r, i, purpose, p)`.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from typing import Optional

import numpy as np
import torch

# independent streams within one batch
INITIAL, CONTROL, RANDOMIZE = 0, 1, 2


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


def batch_seed(seed: int, shard: Shard, index: int, purpose: int) -> np.random.SeedSequence:
    """The seed of one purpose (INITIAL, CONTROL, RANDOMIZE) of global batch `index` (of its
    part `shard.part` when the batch is split across simulation devices)."""
    key = (shard.rank, index, purpose) + ((shard.part,) if shard.parts > 1 else ())
    return np.random.SeedSequence(seed, spawn_key=key)


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def threads_per_worker(shard: Shard, nthread: Optional[int],
                       torch_threads: Optional[int] = None,
                       trains_on_cpu: bool = True) -> int:
    """CPU threads for one worker's simulation: the user's choice, or the cores split evenly
    among this process's workers and the ranks torchrun started on this machine.

    By default the simulation leaves room to the training loop when that may run on the CPU
    (`trains_on_cpu`: batches delivered to the CPU, and torch using more than one intra-op
    thread): it takes half the cores then. Measured on 2 cores: a CPU training loop beside
    2 simulation threads took 1.3x as long as beside 1. Batches delivered to a GPU leave the
    CPU to the simulation: all the cores.
    """
    if nthread is not None:
        return nthread
    local_ranks = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    cores = available_cpus()
    if trains_on_cpu and (torch_threads or 0) > 1:
        cores = max(1, cores // 2)
    return max(1, cores // (shard.num_workers * local_ranks))


def check_nthread(nthread: Optional[int]) -> None:
    """Warns, pointing at the user's SimDataset line, when `nthread` alone asks for more
    threads than the cores: each rollout process oversubscribes the machine."""
    cores = available_cpus()
    if nthread is not None and nthread > cores:
        warnings.warn(
            f"nthread={nthread} asks for more simulation threads than the {cores} cores of this "
            f"machine (per process: DataLoader workers and torchrun ranks each start as many); "
            f"nthread=None splits the cores", RuntimeWarning, stacklevel=4)