"""Splitting one seeded stream across DataLoader workers and torch.distributed ranks.

Every batch has a global index within its rank. Worker `w` of `W` produces the indices
`w, w + W, w + 2W, ...`, which the DataLoader interleaves back into index order, so the stream
a rank sees does not depend on the number of workers (fresh episodes). All randomness of batch
`i` on rank `r` comes from `SeedSequence(seed, spawn_key=(r, i, purpose))`: streams of different
batches, workers and ranks never coincide, and the same seed repeats the whole stream.
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
_warned_oversubscribed = False  # the oversubscription warning: once per process


@dataclasses.dataclass(frozen=True)
class Shard:
    """Where this iterator runs: distributed rank and DataLoader worker."""

    rank: int = 0
    world_size: int = 1
    worker: int = 0
    num_workers: int = 1

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
    """The seed of one purpose (INITIAL, CONTROL, RANDOMIZE) of global batch `index`."""
    return np.random.SeedSequence(seed, spawn_key=(shard.rank, index, purpose))


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def threads_per_worker(shard: Shard, nthread: Optional[int],
                       torch_threads: Optional[int] = None) -> int:
    """CPU threads for one worker's simulation: the user's choice, or the cores split evenly
    among this process's workers and the ranks torchrun started on this machine.

    With the default, warns once per process (from worker 0) when these threads and the
    consumer's torch intra-op threads (`torch_threads`, counted where the dataset was made)
    add up to more than the cores: both busy at once oversubscribe the CPU (measured on 2
    cores: a training loop with 2 + 2 threads took 1.3x as long as with nthread=1).
    """
    if nthread is not None:
        return nthread
    global _warned_oversubscribed
    local_ranks = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
    cores = available_cpus()
    threads = max(1, cores // (shard.num_workers * local_ranks))
    busy = (threads * shard.num_workers + (torch_threads or 0)) * local_ranks
    if torch_threads and busy > cores and shard.worker == 0 and not _warned_oversubscribed:
        _warned_oversubscribed = True
        warnings.warn(
            f"simloader: {threads * shard.num_workers} simulation thread(s) and torch's "
            f"{torch_threads} intra-op thread(s) per process share {cores} cores "
            f"(oversubscribed while the simulation overlaps training: on 2 cores a training "
            f"loop took 1.3x as long). Give SimDataset nthread= or call torch.set_num_threads() "
            f"so that they add up to the cores; passing nthread silences this.",
            RuntimeWarning, stacklevel=2)
    return threads