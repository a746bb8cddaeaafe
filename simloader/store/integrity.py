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

from simloader.store.folder import StoreFolder
from simloader.store.ownership import LEFTOVER, REPLACING, own_names, replacing
from simloader.store.zarr_format import (ATTRIBUTE, CHECKSUM, FORMAT, WRITTEN, DamagedStore,
                                         batch_key, crc_of, recorded)
from simloader.store.shards import ArrayLayout

_MAX_LISTED = 8  # files named in one message; the rest are counted


@dataclasses.dataclass
class Survey:
    metas: dict[str, dict]  # array path -> its zarr.json
    sizes: dict[str, dict[int, int]]  # array path -> {slot: its shard's size}
    links: list[str]  # every link met (never followed), relative to the root
    partial: list[str]  # files of killed writers, relative to the root


# levels below the root: simloader's deepest file is camera/NAME/KIND/c/SLOT/0/0/0/0; a
# hostile store of folders nested thousands deep is refused, not walked until Python's stack
# ends
MAX_DEPTH = 24


def survey(folder: StoreFolder) -> Survey:
    """One walk of the store's own files through its open folder (links are listed, never
    followed): its root's entries, and below them only the store's own folders
    (`ownership.own_names`), so a folder a user put beside the arrays is neither walked nor
    cleaned. Names are relative to the root."""
    metas: dict[str, dict] = {}
    sizes: dict[str, dict[int, int]] = {}
    links: list[str] = []
    partial: list[str] = []
    own = own_names(folder)

    def walk(relative: str, array: Optional[str], below: str) -> None:
        """`relative`: the folder's name; `array`: the array whose chunk folder `c` this is
        in, `below` the path inside it."""
        if relative.count("/") >= MAX_DEPTH:
            raise DamagedStore(f"{folder.where(relative)}: folders nested deeper than any "
                               f"store simloader writes ({MAX_DEPTH} levels); not a store of "
                               f"simloader's, or damaged")
        try:
            entries = folder.entries(relative)
        except FileNotFoundError:
            return  # removed while walked (a resumed writer's repair): seen as absent
        except DamagedStore:
            links.append(relative)  # swapped for a link while walked
            return
        except OSError as e:
            raise DamagedStore(f"{folder.where(relative)}: cannot be listed ({e.strerror})"
                               ) from None
        # files first: an array's zarr.json before its chunk folder `c`
        entries.sort(key=lambda e: e[1] == "folder")
        for name, kind, size in entries:
            rel = f"{relative}/{name}" if relative else name
            inner = f"{below}/{name}" if below else name
            if kind == "link":
                links.append(rel)
            elif LEFTOVER.search(name):
                partial.append(rel)
            elif kind == "folder":
                if not relative and name not in own:
                    continue  # not the store's: left alone
                if array is not None:  # below ARRAY/c/: SLOT/0/0...
                    walk(rel, array, inner)
                elif name == "c" and relative in metas:
                    walk(rel, relative, "")
                else:
                    walk(rel, None, "")
            elif array is not None:
                slot = inner.split("/")[0]
                if slot.isdigit() and kind != "gone":
                    sizes.setdefault(array, {})[int(slot)] = size
            elif name == "zarr.json" and relative:
                meta = folder.read_json(rel)
                if isinstance(meta, dict) and meta.get("node_type") == "array":
                    metas[relative] = meta
    walk("", None, "")
    return Survey(metas, sizes, links, partial)


def marks(folder: StoreFolder) -> dict[int, int]:
    """{slot: size} of the slots' written marks, listed first of all when a store is opened:
    every file a mark commits was on the disk before it, and every metadata file read after
    this listing holds at least the slots it names (a store being grown has grown its
    arrays, its slots' array and then its root before any new slot is marked), so a reader
    sees the committed slots of this one moment, whatever a writer does meanwhile."""
    where = WRITTEN.name + "/c"
    out: dict[int, int] = {}
    try:
        entries = folder.entries(where)
    except (FileNotFoundError, DamagedStore):
        return out  # absent; or a link, which the survey names
    except OSError as e:
        raise DamagedStore(f"{folder.where(where)}: cannot be listed ({e.strerror})") from None
    for name, kind, size in entries:
        if name.isdigit() and kind == "file":
            out[int(name)] = size
    return out


def root_info(folder: StoreFolder) -> dict:
    """The store's root attribute, checked for the fields reading relies on."""
    root, file = folder.path, folder.where("zarr.json")
    meta = folder.read_json("zarr.json")
    if not isinstance(meta, dict) or not isinstance(meta.get("attributes"), dict) or \
            ATTRIBUTE not in meta["attributes"]:
        raise ValueError(f"path: {root!r} is not a simloader store (no zarr.json with a "
                         f"{ATTRIBUTE!r} attribute)")
    info = meta["attributes"][ATTRIBUTE]
    if isinstance(info, dict) and info.get(REPLACING):
        raise DamagedStore(replacing(root))
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

    def __init__(self, folder: StoreFolder, repair: bool = False):
        self.folder = folder
        self.root = root = folder.path
        listed = marks(folder)  # first: see `marks`
        self.info = root_info(folder)
        self.nbatch, self.batches = self.info["nbatch"], self.info["batches"]
        found = survey(folder)
        if found.links:
            raise DamagedStore(f"{root}: the store holds links, which it never writes and "
                               f"never follows (one could alias another slot or lead outside "
                               f"the store): {_listed([folder.where(n) for n in found.links])}")
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
                if self.folder.read(WRITTEN.shard_key(slot), 1) == b"\x01":
                    out.append(slot)
            except FileNotFoundError:
                continue  # unmarked since it was listed (a resumed writer's repair)
        return np.asarray(out, dtype=np.int64)

    def checksums(self, slot: int) -> Optional[dict[str, tuple[int, int]]]:
        """The (size, CRC-32) recorded for each array's shard of a committed slot; None for
        a store written before checksums were recorded."""
        layout = self.layouts.get(CHECKSUM)
        if layout is None:
            return None
        names = layout.attributes.get("arrays")
        try:
            data = self.folder.read(layout.shard_name(slot), 1 << 20)
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
                    crc = crc_of(self.folder, layout.shard_name(slot))
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


def remove_partial(folder: StoreFolder, found: Survey) -> int:
    """Removes the `.partial` files of killed writers (called while holding the store's
    lock: no writer of this store is running), through the store's folder."""
    for name in found.partial:
        folder.unlink(name)
    return len(found.partial)
