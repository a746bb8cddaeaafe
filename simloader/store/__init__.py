"""Keeping the stream: `write` a dataset's batches into a zarr v3 store, `StoredDataset` to
read them back, and the regeneration of any stored trajectory from its provenance.

    format.py      the store on disk: its arrays, shard files and completion marks
    provenance.py  what made a store (configuration, seed, versions), and what may extend it
    writer.py      `write`: workers and ranks fill their own batch slots, no coordinator
    reader.py      `StoredDataset`, `Transitions`, `StoredDataset.regenerate`
    minari.py      `write(format="minari")`: a Minari dataset instead
"""

from simloader.store.reader import StoredDataset, Transitions
from simloader.store.writer import write

__all__ = ["StoredDataset", "Transitions", "write"]
