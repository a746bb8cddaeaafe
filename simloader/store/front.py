"""`simloader.write`, the store's front: checks the arguments every format takes and hands
them to the format's writer (the table in `simloader.store.formats`).

The front imports the table, the table the writers; no writer imports either back.
"""

from __future__ import annotations

import os
from typing import Any, Optional

from simloader.store import formats, mixture_store
from simloader.store.zarr_format import COMPRESSIONS


def write(dataset: Any, path: str | os.PathLike, *, batches: int, format: str = "zarr",
          num_workers: int = 0, progress: bool = True, replace: bool = False,
          compression: Optional[str] = None) -> str:
    """Streams `batches` batches of `dataset` into a store at `path` and returns the path.

    `format="zarr"`: a zarr v3 group (see `simloader.store.zarr_format` for the layout);
    every batch key becomes an array `batches * nbatch x ...` in its own dtype. `batches` counts
    all ranks' batches: under torchrun each rank calls `write` with the same arguments and
    writes its own slots. `num_workers > 0` simulates and writes in DataLoader workers, each
    its own slots.

    Each writer is a pipeline (`simloader.store.pipeline`): the next batches simulate while a
    batch is copied to the host (pinned memory, asynchronously, for GPU batches), checksummed,
    compressed and written over threads, and committed. At most `prefetch + 3` batches per
    worker are in memory, 2 of them in (pinned) host memory. The zarr writer returns the path
    with a `report` attribute (`pipeline.WriteReport`): the seconds of each stage (simulate,
    copy to host, compress, checksum, write, sync) and which one bounded the run.

    `compression`: None stores floating-point arrays raw (MuJoCo's states compress little:
    1.05-1.4x); "zstd" compresses them too, with zarr's blosc codec (byte shuffle, zstd level
    1), which costs CPU (about 40-300 MB/s per slot's chunks, measured) and pays only where
    the disk is slower still. Images are compressed with zstd either way.

    One job writes a store at a time: the store's lock (`simloader.store.lock`) is held from
    start to end, and a second process is refused at once, naming the holder. A killed
    writer's lock is taken over. Every slot is committed durably (fsync'd files and
    directories) with each shard's size and CRC-32.

    An existing store of the same configuration is resumed: every committed slot is checked
    (sizes and checksums, every byte read) and the damaged ones are written again with the
    missing ones (a killed writer loses the batches in flight only; files it left half
    written are removed), and a larger `batches` appends. One of another configuration or
    simulator version is refused, naming what differs; `replace=True` removes it first.

    `dataset` may be a `simloader.Mixture`: each task's batches (those the mixture yields with
    `num_workers=0`) go into a store of their own under `path/tasks/`, and
    `simloader.open_store(path)` reads them back as one dataset with `"task"` (see
    `simloader.store.mixture_store`).

    `format="minari"`: a Minari dataset (see `simloader.store.minari`), named after the last
    component of `path`, under its parent directory.

    Raises:
      ValueError: bad arguments; a store of another configuration at `path`; a store whose
        metadata is damaged (`DamagedStore`, naming the file).
      ~simloader.store.StoreLocked: another job is writing the store.
      OSError: the disk is full or not writable (the store stays readable, holding the
        batches completed so far; writing again resumes).
    """
    if not isinstance(batches, int) or isinstance(batches, bool) or batches < 1:
        raise ValueError(f"batches: expected a positive int, got {batches!r}")
    if not isinstance(num_workers, int) or num_workers < 0:
        raise ValueError(f"num_workers: expected an int >= 0, got {num_workers!r}")
    if not isinstance(replace, bool):
        raise ValueError(f"replace: expected True or False, got {replace!r}")
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression: expected one of {list(COMPRESSIONS)}, got "
                         f"{compression!r}")
    path = os.fspath(path)
    chosen = formats.get(format)
    if mixture_store.is_mixture(dataset):
        if format != "zarr":
            raise ValueError(f"format={format!r}: a Mixture is written as a zarr store of its "
                             f"tasks' stores (format='zarr'); write each member for "
                             f"{format!r}")
        return mixture_store.write_mixture(dataset, path, batches=batches,
                                           num_workers=num_workers, progress=progress,
                                           replace=replace, compression=compression)
    options = {} if compression is None else {"compression": compression}
    if options and not chosen.compresses:
        raise ValueError(f"compression={compression!r}: the {format!r} format keeps its own "
                         f"encoding; compression applies to format='zarr'")
    return chosen.write(dataset, path, batches=batches, num_workers=num_workers,
                        progress=progress, replace=replace, **options)

