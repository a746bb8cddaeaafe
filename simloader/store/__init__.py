"""Keeping the stream: `write` a dataset's batches into a zarr v3 store, `StoredDataset` to
read them back, and the regeneration of any stored trajectory from its provenance.

    zarr_format.py      the store on disk: its arrays, names, shard files, checksums and marks
    shards.py           reading shard files: layouts checked, a bounded table of open shards
    integrity.py        one walk of a store's files; committed slots checked against their sizes
                        and checksums; leftovers of killed writers
    folder.py           a store's folder held open: every file of a write reached relative to
                        it, no link followed
    ownership.py        what a writer may touch: the store's own entries, no store inside one
    lock.py             one writer job per store
    order.py            the orders an epoch reads a store in (quasi-random, random, sequential)
    provenance.py       what made a store (configuration, seed, versions), and what may extend it
    front.py            `write`: its arguments checked, handed to the format's writer
    formats.py          the table of formats: each one's name, writer and how to read it back
    writer.py           `write(format="zarr")`: workers and ranks fill their own batch slots under
                        one lock
    pipeline.py         a writer's slots from the simulator to a durable commit, its stages
                        overlapped; the per-stage report
    mixture_store.py    a Mixture in a store: one store per task under tasks/, read back as one
                        dataset with "task"
    reader.py           `StoredDataset`, `Transitions`, `StoredDataset.regenerate`
    (here)              `open_store`: the explicit opener, a mixture's store or one stream's
    minari.py           `write(format="minari")`: a Minari dataset instead; `write_minari`, `status`
    minari_episodes.py  a batch's trajectories as Minari episodes, the action space
    minari_folder.py    a Minari dataset's directory: what is there, its lock, what killed
                        writers left, its removal
    minari_metadata.py  Minari's metadata.json and simloader's progress record in it
    minari_hdf5.py      its HDF5 files, never modified in place: creation, batch files,
                        resuming, the assembly of main_data.hdf5
"""

import os

from simloader.store.zarr_format import DamagedStore
from simloader.store.folder import StoreChanged
from simloader.store.lock import StoreLocked
from simloader.store.shards import StoreReplaced
from simloader.store.reader import StoredDataset
from simloader.store.transitions import Transitions
from simloader.store.front import write

from simloader.store.mixture_store import StoredMixture, mixture_root

__all__ = ["DamagedStore", "StoreChanged", "StoreLocked", "StoreReplaced", "StoredDataset",
           "StoredMixture", "Transitions", "open_store", "write"]


def open_store(path, **kwargs):
    """The store at `path` read back, whichever kind `simloader.write` made there: a
    `StoredMixture` for a mixture's store (one store per task, read as one dataset with
    `"task"`), else a `StoredDataset`. `kwargs` are theirs (`keys`, `verify`, `cameras`,
    `backend`, `device`, `model`)."""
    if mixture_root(os.fspath(path)) is not None:
        return StoredMixture(path, **kwargs)
    return StoredDataset(path, **kwargs)
