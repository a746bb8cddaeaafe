"""The formats `write` (and `simloader write --format`) writes: one entry a format, its name,
what it is, its writer and how to read it back. A new format is one more entry here.

Each writer is called as `write(dataset, path, batches=, num_workers=, progress=, replace=)`
after `simloader.store.write` has checked those arguments; it is imported only when its
format is written (Minari is an extra).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable, Optional


@dataclass(frozen=True)
class Format:
    name: str
    description: str
    write: Callable[..., str]  # (dataset, path, *, batches, num_workers, progress, replace)
    read_hint: Optional[str] = None  # how to read it back, "{path!r}" filled in, if simloader can


def _write_zarr(dataset: Any, path: str, **kwargs: Any) -> str:
    from simloader.store import writer
    return writer.write_zarr(dataset, path, **kwargs)


def _write_minari(dataset: Any, path: str, *, batches: int, num_workers: int,
                  progress: bool, replace: bool) -> str:
    from simloader.store import minari
    from simloader.store.provenance import provenance
    # minari.write streams the dataset in this process: num_workers is not used
    return minari.write(dataset, path, batches=batches, progress=progress,
                        metadata=provenance(dataset, batches), replace=replace)


FORMATS: dict[str, Format] = {f.name: f for f in (
    Format("zarr", "a zarr v3 group (`simloader.store.zarr_format`), read by StoredDataset",
           _write_zarr,
           read_hint="read them with simloader.StoredDataset({path!r}) or any zarr v3 reader"),
    Format("minari", "a Minari dataset (`simloader.store.minari`, extra `minari`)",
           _write_minari),
)}


def get(name: Any) -> Format:
    """The format named `name`; a ValueError naming the formats otherwise."""
    if isinstance(name, str) and name in FORMATS:
        return FORMATS[name]
    known = " or ".join(repr(n) for n in FORMATS)
    raise ValueError(f"format: expected {known}, got {name!r}")


def read_hint(name: str, path: str | os.PathLike) -> Optional[str]:
    """How to read back a store of format `name` at `path`, or None where simloader has none."""
    hint = FORMATS[name].read_hint
    return None if hint is None else hint.format(path=os.fspath(path))
