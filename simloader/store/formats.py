"""The formats `write` (and `simloader write --format`) writes: one entry a format, its name,
what it is, its writer and how to read it back. A new format is one more entry here.

Each writer is called as `write(dataset, path, batches=, num_workers=, progress=, replace=)`
(and `compression=` where the format says it takes it) after `simloader.store.front.write`
has checked those arguments. The zarr writer is imported with this table; Minari's only when
its format is written (Minari is an extra). No writer imports this table or the front back.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable, Optional

from simloader.store import writer


@dataclass(frozen=True)
class Format:
    name: str
    description: str
    write: Callable[..., str]  # (dataset, path, *, batches, num_workers, progress, replace)
    read_hint: Optional[str] = None  # how to read it back, "{path!r}" filled in, if simloader can
    compresses: bool = False  # takes `compression=`


def _write_minari(dataset: Any, path: str, **kwargs: Any) -> str:
    from simloader.store import minari
    return minari.write(dataset, path, **kwargs)


FORMATS: dict[str, Format] = {f.name: f for f in (
    Format("zarr", "a zarr v3 group (`simloader.store.zarr_format`), read by StoredDataset",
           writer.write_zarr,
           read_hint="read them with simloader.StoredDataset({path!r}) or any zarr v3 reader",
           compresses=True),
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
