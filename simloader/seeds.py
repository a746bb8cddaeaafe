"""Where every random draw of a batch comes from.

All randomness of batch `i` on rank `r` comes from `SeedSequence(seed, spawn_key=(r, i,
purpose))`: streams of different batches, workers and ranks never coincide, and the same seed
repeats the whole stream. A batch split across several simulation devices (`sim_device=`)
draws each part `p` from `spawn_key=(r, i, purpose, p)`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# independent streams within one batch
INITIAL, CONTROL, RANDOMIZE, RESET = 0, 1, 2, 3


def batch_seed(seed: int, shard: Any, index: int, purpose: int) -> np.random.SeedSequence:
    """The seed of one purpose (INITIAL, CONTROL, RANDOMIZE) of global batch `index` (of its
    part `shard.part` when the batch is split across simulation devices)."""
    key = (shard.rank, index, purpose) + ((shard.part,) if shard.parts > 1 else ())
    return np.random.SeedSequence(seed, spawn_key=key)


def reset_seed(seed: int, shard: Any, index: int, draw: int) -> np.random.SeedSequence:
    """The seed of global batch `index`'s `draw`-th set of fresh initial states, one per
    trajectory (`terminate=`'s autoreset: a trajectory's e-th reset of the batch takes its
    row of set `e % terminate.FRESH_DRAWS`)."""
    base = batch_seed(seed, shard, index, RESET)
    return np.random.SeedSequence(seed, spawn_key=base.spawn_key + (draw,))
