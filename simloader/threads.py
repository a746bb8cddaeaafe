"""How many CPU threads each simulation takes: the cores split among DataLoader workers and
the ranks torchrun started on this machine."""

from __future__ import annotations

import os
import warnings
from typing import Any, Optional


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def threads_per_worker(shard: Any, nthread: Optional[int],
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
            f"nthread=None splits the cores", RuntimeWarning, stacklevel=5)
