"""Keeping the stream: `write` a dataset's batches into a zarr v3 store, `StoredDataset` to
read them back, and the regeneration of any stored trajectory from its provenance.

    zarr_format.py the store on disk: its arrays, names, shard files, checksums and marks
    shards.py      reading shard files: layouts checked, a bounded table of open shards
    integrity.py   one walk of a store's files; committed slots checked against their sizes
                   and checksums; leftovers of killed writers
    lock.py        one writer job per store
    order.py       the orders an epoch reads a store in (quasi-random, random, sequential)
    provenance.py  what made a store (configuration, seed, versions), and what may extend it
    writer.py      `write`: workers and ranks fill their own batch slots under one lock
    reader.py      `StoredDataset`, `Transitions`, `StoredDataset.regenerate`
    minari.py      `write(format="minari")`: a Minari dataset instead
"""

from simloader.store.zarr_format import DamagedStore
from simloader.store.lock import StoreLocked
from simloader.store.reader import StoredDataset, Transitions
from simloader.store.writer import write

__all__ = ["DamagedStore", "StoreLocked", "StoredDataset", "Transitions", "write"]
