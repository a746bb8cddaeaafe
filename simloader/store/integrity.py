"""What a store holds, checked against what it says: one walk of its files at open, the sizes
and checksums of every committed slot, and the leftovers of killed writers.

`survey` walks the store once (never probing slots one by one, so an edited `batches` of
10^9 costs nothing) and returns each array's metadata, each shard's size, the links and the
`.partial` files it met. `Store.check` holds every committed slot to its layout and its
recorded checksums; `damaged` is used both by the reader (which refuses a damaged store,
naming the files) and by a resumed writer (which rewrites those slots).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any, Optional

import numpy as np

from simloader.store.ownership import LEFTOVER, own_folder
from simloader.store.zarr_format import (ATTRIBUTE, CHECKSUM, FORMAT, WRITTEN, DamagedStore,
                                         batch_key, file_crc, read_json, recorded)
from simloader.store.shards import ArrayLayout

_MAX_LISTED = 8  # files named in one message; the rest are counted


@dataclasses.dataclass
class Survey:
    metas: dict[str, dict]  # array path -> its zarr.json
    sizes: dict[str, dict[int, int]]  # array path -> {slot: its shard's size}
    links: list[str]  # every link met (never followed)
    partial: list[str]  # files of killed writers


def survey(root: str) -> Survey:
    """One walk of the store's own files (links are listed, not followed): its root's
    entries, and below them only the store's folders (`ownership.own_folder`), so a folder a
    user put beside the arrays is neither walked nor cleaned."""
    metas: dict[str, dict] = {}
    sizes: dict[str, dict[int, int]] = {}
    links: list[str] = []
    partial: list[str] = []

    def walk(directory: str, relative: str, array: Optional[str]) -> None:
        try:
            entries = list(os.scandir(directory))
        except FileNotFoundError:
            return  # removed while walked (a resumed writer's repair): seen as absent
        except OSError as e:
            raise DamagedStore(f"{directory}: cannot be listed ({e.strerror})") from None
        # files first: an array's zarr.json before its chunk folder `c`
        entries.sort(key=lambda e: _is_dir(e))
        for entry in entries:
            rel = f"{relative}/{entry.name}" if relative else entry.name
            if entry.is_symlink():
                links.append(entry.path)
            elif LEFTOVER.search(entry.name):
                partial.append(entry.path)
            elif _is_dir(entry):
                if not relative and array is None and not own_folder(entry.path):
                    continue  # not the store's: left alone
                if array is not None:  # below ARRAY/c/: SLOT/0/0...
                    walk(entry.path, rel, array)
                elif entry.name == "c" and relative in metas:
                    walk(entry.path, "", relative)
                else:
                    walk(entry.path, rel, None)
            elif array is not None:
                slot = rel.split("/")[0]
                if slot.isdigit():
                    try:
                        size = entry.stat(follow_symlinks=False).st_size
                    except FileNotFoundError:
                        continue
                    sizes.setdefault(array, {})[int(slot)] = size
            elif entry.name == "zarr.json" and relative:
                meta = read_json(entry.path)
                if isinstance(meta, dict) and meta.get("node_type") == "array":
                    metas[relative] = meta
    walk(root, "", None)
    return Survey(metas, sizes, links, partial)


def _is_dir(entry: os.DirEntry) -> bool:
    try:
        return entry.is_dir(follow_symlinks=False)
    except OSError:
        return False


def marks(root: str) -> dict[int, int]:
    """{slot: size} of the slots' written marks, listed first of all when a store is opened:
    every file a mark commits was on the disk before it, and every metadata file read after
    this listing holds at least the slots it names (a store being grown has grown its
    arrays, its slots' array and then its root before any new slot is marked), so a reader
    sees the committed slots of this one moment, whatever a writer does meanwhile."""
    folder = os.path.join(root, WRITTEN.name, "c")
    out: dict[int, int] = {}
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        return out
    except OSError as e:
        raise DamagedStore(f"{folder}: cannot be listed ({e.strerror})") from None
    for entry in entries:
        if entry.name.isdigit() and not entry.is_symlink():
            try:
                out[int(entry.name)] = entry.stat(follow_symlinks=False).st_size
            except FileNotFoundError:
                pass
    return out


def root_info(root: str) -> dict:
    """The store's root attribute, checked for the fields reading relies on."""
    file = os.path.join(root, "zarr.json")
    meta = read_json(file)
    if not isinstance(meta, dict) or not isinstance(meta.get("attributes"), dict) or \
            ATTRIBUTE not in meta["attributes"]:
        raise ValueError(f"path: {root!r} is not a simloader store (no zarr.json with a "
                         f"{ATTRIBUTE!r} attribute)")
    info = meta["attributes"][ATTRIBUTE]
    version = info.get("format") if isinstance(info, dict) else info
    if version != FORMAT:
        raise ValueError(f"path: store format {version!r}, this simloader reads format "
                         f"{FORMAT} ({file})")
    for field, least in (("nbatch", 1), ("batches", 0), ("record_every", 1)):
        value = info.get(field)
        if not isinstance(value, int) or isinstance(value, bool) or value < least:
            raise DamagedStore(f"{file}: the attribute {ATTRIBUTE}.{field} is {value!r}, "
                               f"expected an int >= {least}")
    return info


class Store:
    """A store's layout and committed slots at one moment, checked against its files at open.

    `problems` names the arrays whose metadata is missing or differs from what the checksums'
    record kept (`zarr_format.checksum_spec`): a reader is refused them at once (`check`); a
    resumed writer (`repair=True`) restores them from the record."""

    def __init__(self, root: str, repair: bool = False):
        self.root = root
        listed = marks(root)  # first: see `marks`
        self.info = root_info(root)
        self.nbatch, self.batches = self.info["nbatch"], self.info["batches"]
        found = survey(root)
        if found.links:
            raise DamagedStore(f"{root}: the store holds links, which it never writes and "
                               f"never follows (one could alias another slot or lead outside "
                               f"the store): {_listed(found.links)}")
        self.survey = found
        self.slots = self._committed(listed)
        self.layouts: dict[str, ArrayLayout] = {}
        checks = found.metas.get(CHECKSUM)
        record = (checks.get("attributes") or {}).get("metadata") if checks else None
        self.record: dict[str, dict] = record if isinstance(record, dict) else {}
        self.problems: dict[str, str] = {}  # array path -> what is wrong with its metadata
        if checks is None and len(self.slots):
            self.problems[CHECKSUM] = (f"{os.path.join(root, CHECKSUM, 'zarr.json')}: "
                                       f"missing, but slots are committed: the store cannot "
                                       f"say which arrays it holds")
        for path, kept in self.record.items():
            meta = found.metas.get(path)
            file = os.path.join(root, path, "zarr.json")
            if meta is None:
                self.problems[path] = (f"{file}: missing: the store's array {path!r} (batch "
                                       f"key {batch_key(path, kept)!r}) is gone")
            elif recorded(meta) != kept:
                differ = [f"{k} {meta.get(k)!r}, written as {kept.get(k)!r}"
                          for k in sorted(set(meta) | set(kept))
                          if k != "shape" and meta.get(k) != kept.get(k)]
                if recorded(meta)["shape"] != kept.get("shape"):
                    differ.insert(0, f"trailing shape {meta.get('shape', [None])[1:]}, "
                                     f"written as {kept.get('shape', [None])[1:]}")
                self.problems[path] = (f"{file}: edited: {'; '.join(differ)} (the array's "
                                       f"files hold what was written)")
        for path, meta in found.metas.items():
            if path in self.problems:
                continue
            rows = 1 if path in (WRITTEN.name, CHECKSUM) else self.nbatch
            self.layouts[path] = ArrayLayout.parse(root, path, meta, rows)
        if not repair:
            self.check()
        written = self.layouts.get(WRITTEN.name)
        if written is None:
            raise DamagedStore(f"{os.path.join(root, WRITTEN.name, 'zarr.json')}: missing; "
                               f"the store cannot say which slots are complete")
        # the slots' array grows before the root does: larger while a writer grows the store
        if written.shape[0] < self.batches:
            raise DamagedStore(f"{os.path.join(root, 'zarr.json')}: the attribute "
                               f"{ATTRIBUTE}.batches is {self.batches}, but {written.file} "
                               f"has {written.shape[0]} slots")
        for layout in self.layouts.values():
            needed = (int(self.slots[-1]) + 1) * layout.nbatch if len(self.slots) else 0
            if layout.shape[0] < needed:
                raise DamagedStore(f"{layout.file}: {layout.shape[0]} rows, but slot "
                                   f"{int(self.slots[-1])} is committed and needs {needed}")

    def check(self) -> None:
        """Refuses a store with `problems` (`DamagedStore`, naming each file)."""
        if self.problems:
            raise DamagedStore(f"the store at {self.root!r} is damaged: "
                               f"{_listed(list(self.problems.values()))}. Calling "
                               f"simloader.write again with the same dataset restores it")

    def _committed(self, sizes: dict[int, int]) -> np.ndarray:
        """The committed slots: a written mark of one byte `1` (zarr's raw shard: the byte,
        then its index of 16)."""
        out = []
        for slot in sorted(sizes):
            file = os.path.join(self.root, WRITTEN.shard_key(slot))
            if slot >= self.batches:
                raise DamagedStore(f"{file}: slot {slot} is marked written, but the store's "
                                   f"root says it has {self.batches} slots")
            if sizes[slot] != 17:
                continue  # not a mark simloader wrote: the slot is not committed
            try:
                fd = os.open(file, os.O_RDONLY | os.O_NOFOLLOW)
            except FileNotFoundError:
                continue  # unmarked since it was listed (a resumed writer's repair)
            with os.fdopen(fd, "rb") as f:
                if f.read(1) == b"\x01":
                    out.append(slot)
        return np.asarray(out, dtype=np.int64)

    def checksums(self, slot: int) -> Optional[dict[str, tuple[int, int]]]:
        """The (size, CRC-32) recorded for each array's shard of a committed slot; None for
        a store written before checksums were recorded."""
        layout = self.layouts.get(CHECKSUM)
        if layout is None:
            return None
        names = layout.attributes.get("arrays")
        file = layout.shard_file(self.root, slot)
        try:
            with open(file, "rb") as f:
                data = f.read()
        except FileNotFoundError:
            return {}  # committed before its checksums: damaged (see `damaged`)
        count = layout.trailing[0]
        if not isinstance(names, list) or len(names) != count or len(data) != 16 * count + 16:
            return {}
        values = np.frombuffer(data[:16 * count], dtype="<u8").reshape(count, 2)
        return {n: (int(v[0]), int(v[1])) for n, v in zip(names, values)}

    def damaged(self, slots: Any = None, verify: bool = False,
                progress: Any = None) -> dict[int, list[str]]:
        """{slot: what is wrong with each of its files} for the committed `slots` (default
        all): a missing shard, a size other than its layout's or its recorded one, and with
        `verify` a CRC-32 other than the recorded one (every byte read)."""
        out: dict[int, list[str]] = {}
        arrays = [l for p, l in self.layouts.items() if p not in (WRITTEN.name, CHECKSUM)
                  and not l.empty]
        for slot in (self.slots if slots is None else slots):
            slot = int(slot)
            recorded = self.checksums(slot)
            problems = []
            if recorded == {}:
                problems.append(f"{os.path.join(self.root, CHECKSUM)}: the checksums of slot "
                                f"{slot} are missing or malformed")
            for layout in arrays:
                file = layout.shard_file(self.root, slot)
                size = self.survey.sizes.get(layout.path, {}).get(slot)
                raw = layout.raw_bytes  # what the metadata says: dtype x shape + the index
                kept = recorded.get(layout.path, (None,))[0] if recorded else None
                if size is None:
                    problems.append(f"{file}: missing")
                elif raw is not None and size != raw:
                    problems.append(f"{file}: {size} bytes, expected {raw} "
                                    f"({'x'.join(map(str, layout.shard_shape))} "
                                    f"{layout.dtype.name} and a chunk index, as "
                                    f"{layout.file} says)")
                elif kept is not None and size != kept:
                    problems.append(f"{file}: {size} bytes, {kept} when it was written")
                elif verify and recorded and layout.path in recorded:
                    crc = file_crc(file)
                    if crc != recorded[layout.path][1]:
                        problems.append(f"{file}: CRC-32 {crc:08x}, recorded "
                                        f"{recorded[layout.path][1]:08x}")
            if problems:
                out[slot] = problems
            if progress is not None:
                progress(1)
        return out


def describe_damage(root: str, damage: dict[int, list[str]]) -> str:
    files = [p for slot in sorted(damage) for p in damage[slot]]
    return (f"the store at {root!r} has {len(damage)} damaged batch slot(s) "
            f"{sorted(damage)[:_MAX_LISTED]}{' ...' if len(damage) > _MAX_LISTED else ''}: "
            f"{_listed(files)}. Calling simloader.write again with the same dataset rewrites "
            f"them (it checks every committed slot and redoes the damaged ones)")


def _listed(items: list[str]) -> str:
    shown = "; ".join(items[:_MAX_LISTED])
    return shown + (f"; and {len(items) - _MAX_LISTED} more" if len(items) > _MAX_LISTED else "")


def remove_partial(found: Survey) -> int:
    """Removes the `.partial` files of killed writers (called while holding the store's
    lock: no writer of this store is running)."""
    removed = 0
    for file in found.partial:
        try:
            os.unlink(file)
            removed += 1
        except FileNotFoundError:
            pass
    return removed
