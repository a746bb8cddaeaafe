"""How much memory a batch needs, and refusing one that cannot fit where it is made."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np


def batch_nbytes(observations: Sequence[Any], nbatch: int, nframes: int, nstep: int,
                 ncontrol: int, nstate: int, itemsize: Optional[int] = None) -> int:
    """Bytes of one batch: the recorded buffers (`Record.buffer`: shared ones counted once),
    `control`,
    `initial_state` and `diverged`.

    Args:
      itemsize: bytes per floating value where the target stores floats in another precision
        (4 for MJX's float32); None: MuJoCo's (8).
    """
    def nbytes(dtype: np.dtype, count: int) -> int:
        size = itemsize if itemsize is not None and dtype.kind == "f" else dtype.itemsize
        return size * count

    total, buffers = 0, set()
    for o in observations:
        buffer, values = o.buffer
        if buffer in buffers:
            continue
        buffers.add(buffer)
        total += nbytes(o.dtype, nbatch * nframes * values)
    f64 = np.dtype(np.float64)
    return (total + nbytes(f64, nbatch * nstep * ncontrol) + nbytes(f64, nbatch * nstate)
            + nbatch)


def check_batch_fits(config: Any, available: int, where: str, *, count: int,
                     itemsize: Optional[int] = None) -> None:
    """Refuses a batch of `config` (a `SimConfig`) whose `count` copies in flight need more than
    `available` bytes of `where` ("host memory", "GPU memory"); `itemsize` as `batch_nbytes`.

    Raises:
      ValueError: naming `nbatch` and `record`, with the size, what is available and what to
        reduce.
    """
    c = config
    nbytes = batch_nbytes(c.observations, c.nbatch, c.nframes, c.nstep, c.ncontrol, c.nstate,
                          itemsize)
    check_fits(nbytes, available, where, nbatch=c.nbatch, nstep=c.nstep,
               record_every=c.record_every, count=count)


def check_fits(nbytes: int, available: int, where: str, *, nbatch: int, nstep: int,
               record_every: int, count: int = 1) -> None:
    """Refuses a batch of `nbytes` whose `count` copies in flight need more than `available`
    bytes.

    Raises:
      ValueError: with the size, what is available and what to reduce: `nbatch`, or `nstep`
        where not even one trajectory fits.
    """
    if nbytes * count <= available:
        return
    needed = f"{_gib(nbytes)}" + (f" each, {count} in flight ({_gib(nbytes * count)})"
                                  if count > 1 else "")
    fits = nbatch * available // (nbytes * count)
    if fits < 1:  # one trajectory is too long: fewer trajectories would not help
        steps = nstep * available // (-(-nbytes // nbatch) * count)
        raise ValueError(
            f"nstep: a batch of {nbatch} trajectories of {nstep} steps needs {needed}, more "
            f"than the {_gib(available)} of {where} available, and one trajectory alone does "
            f"not fit; use a smaller nstep (about {steps} steps fit with nbatch=1), a larger "
            f"record_every (now {record_every}) or fewer record fields, and continue_episodes="
            f"True for longer episodes")
    raise ValueError(
        f"nbatch, record: a batch needs {needed}, more than the {_gib(available)} of {where} "
        f"available; use a smaller nbatch (at most {fits} fits), a larger record_every (now "
        f"{record_every}), fewer or smaller record fields, or fewer batches in flight "
        f"(prefetch)")


def _gib(n: int) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**27 else f"{n / 2**20:.1f} MiB"


def host_available() -> int:
    """Bytes of host memory available now (Linux MemAvailable; else the physical pages
    free)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import os
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
