"""What a store's writer may touch: the store's own files, nothing else.

A path handed to `write` is not permission to empty a folder. Before anything is opened for
writing, the target must be one of:

- a path that does not exist yet, or an empty folder (a new store);
- a simloader store (a root `zarr.json` with the `simloader` attribute): resumed, extended,
  or with `replace=True` replaced;
- what a killed creation left (the lock and `provenance/` only: the slots' array and the
  models): taken over.

Anything else (a project folder, another tool's zarr group, a file) is refused, naming what is
there, and so are system folders (`/`, `/usr`, the home folder, ...), whatever they hold. A
store's own entries are its root `zarr.json`, its lock, `provenance/`, a mixture store's
`tasks/`, and the arrays and groups simloader writes (an array's `zarr.json` names its batch
key; a group holds nothing else); `replace=True` removes those and leaves any other entry a
user put beside them, a zarr group of their own included. A link anywhere among them is
refused before the lock is taken: a lock or a folder that links outside the store would have
the writer empty or write a file that is not its own.

No store is made inside another (its readers would refuse the outer store as damaged, and a
`replace=True` of the outer one would remove it): a path below a store's root is refused,
naming the outer store, but for a mixture store's own members under its `tasks/`.

Everything after the first checks by path goes through the store's open folder
(`simloader.store.folder`): no link is followed, whatever is swapped in meanwhile.
"""

from __future__ import annotations

import errno
import os
import re
from typing import Optional

from simloader.atomic import PARTIAL
from simloader.store.folder import StoreFolder
from simloader.store.lock import FILE as LOCK
from simloader.store.provenance import new_identity
from simloader.store.zarr_format import ATTRIBUTE, CHECKSUM, FORMAT, DamagedStore

ROOT = "zarr.json"
_CREATION = frozenset({LOCK, "provenance"})  # what a creation makes before its root
# the temporary names `atomic_write` gives (NAME.<32 hex>.partial): only those are a killed
# writer's, a user's `download.partial` is not
LEFTOVER = re.compile(r"\.[0-9a-f]{32}" + re.escape(PARTIAL) + r"$")
_SYSTEM = ("/", "/bin", "/boot", "/dev", "/etc", "/home", "/lib", "/lib32", "/lib64", "/libx32",
           "/media", "/mnt", "/opt", "/proc", "/root", "/run", "/sbin", "/srv", "/sys", "/tmp",
           "/usr", "/usr/bin", "/usr/include", "/usr/lib", "/usr/lib64", "/usr/local",
           "/usr/local/bin", "/usr/local/lib", "/usr/sbin", "/usr/share", "/var", "/var/lib",
           "/var/log", "/var/tmp", "/snap", "/nix", "/System", "/Library", "/Applications",
           "/Users", "/Volumes", "/private")
_NEVER_BELOW = ("/proc", "/sys", "/dev")
_SHOWN = 6  # entries named in a refusal
_GROUP_DEPTH = 3  # camera/NAME/KIND: the deepest group simloader makes above an array


class NotAStore(ValueError):
    """`write`'s path is not one a store may be written to (a folder of the user's, a system
    folder, a file, a path inside another store); nothing was written or deleted."""


def system_folder(path: str) -> bool:
    """`path` (resolved) is a system folder or the home folder, or lies in a kernel's one."""
    real = os.path.realpath(path)
    home = os.path.realpath(os.path.expanduser("~"))
    return (real in _SYSTEM or real == home or
            any(real.startswith(top + "/") for top in _NEVER_BELOW))


def root_attribute(folder: StoreFolder) -> Optional[dict]:
    """The `simloader` attribute of the folder's root `zarr.json` (a file, not a link), or
    None where there is none."""
    try:
        meta = folder.read_json(ROOT)
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or not isinstance(meta.get("attributes"), dict):
        return None
    value = meta["attributes"].get(ATTRIBUTE)
    return value if isinstance(value, dict) else None


def is_store_root(path: str) -> bool:
    """`path` holds a root `zarr.json` (a file, not a link) with the `simloader` attribute."""
    try:
        with StoreFolder(path) as folder:
            return root_attribute(folder) is not None
    except (OSError, ValueError):
        return False


def _listed(names: list[str]) -> str:
    names = sorted(names)
    shown = ", ".join(repr(n) for n in names[:_SHOWN])
    return shown + (f" and {len(names) - _SHOWN} more" if len(names) > _SHOWN else "")


def check_path(path: str) -> None:
    """The checks by path, before anything is opened: a path at all, not a system folder,
    not a file or a link to nothing, not inside another store (a mixture's members are
    opened through its folder instead). Reads only."""
    if path == "":
        raise NotAStore("path: expected the folder of a store, got an empty path")
    if "\0" in path:
        raise NotAStore(f"path: {path!r} holds a NUL character, which no file name can")
    _check_names(path)
    if system_folder(path):
        raise NotAStore(f"path: {path!r} is a system folder ({os.path.realpath(path)}); a "
                        f"store is written into a folder of its own: pass a new folder, e.g. "
                        f"{os.path.join(path, 'trajectories.zarr')!r}")
    if os.path.islink(path) and not os.path.exists(path):
        raise NotAStore(f"path: {path!r} is a link to {os.readlink(path)!r}, which does not "
                        f"exist; pass the folder itself (or create the link's target)")
    if os.path.lexists(path) and not os.path.isdir(path):
        raise NotAStore(f"path: {path!r} is a file, not a folder; a store is a folder: pass a "
                        f"new path")
    outer = enclosing_store(path)
    if outer is not None:
        raise NotAStore(f"path: {path!r} lies inside the store at {outer!r}; a store inside "
                        f"a store makes the outer one unreadable (its readers refuse what "
                        f"they do not know) and a replace=True of the outer one would remove "
                        f"it: write to a path outside {outer!r}")


def _check_names(path: str) -> None:
    """Every name of `path` fits the file system, and a `..` comes after folders that exist
    (`new/../store.zarr` would make `new` and then write elsewhere than it says)."""
    parts = path.split(os.sep)
    for k, part in enumerate(parts):
        if part == "..":
            before = os.sep.join(parts[:k]) or (os.sep if path.startswith(os.sep) else ".")
            if not os.path.isdir(before):
                raise NotAStore(f"path: {path!r} goes up ('..') from {before!r}, which is not "
                                f"a folder; pass the path without '..'")
        elif len(part.encode()) > (most := _name_max(os.sep.join(parts[:k]) or ".")):
            raise NotAStore(f"path: the name {part[:40]!r}... of {path[:60]!r}... is "
                            f"{len(part.encode())} bytes, longer than the file system allows "
                            f"({most}); pass a shorter name")


def _name_max(folder: str) -> int:
    """The longest name the file system of `folder` (or of the nearest folder above it that
    exists) takes."""
    while folder and not os.path.isdir(folder):
        folder = os.path.dirname(folder)
    try:
        return int(os.pathconf(folder or ".", "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def enclosing_store(path: str) -> Optional[str]:
    """The nearest folder above `path` (resolved) that is a store's root, or None."""
    real = os.path.realpath(path)
    above = os.path.dirname(real)
    while True:
        if is_store_root(above):
            return above
        parent = os.path.dirname(above)
        if parent == above:
            return None
        above = parent


def check_contents(folder: StoreFolder, replace: bool) -> None:
    """Refuses (`NotAStore`) a folder a store may not be written to: anything but an empty
    folder, a simloader store or a killed creation; and links among a store's own entries.
    Reads only, through the open folder."""
    entries = {name: kind for name, kind, _ in folder.entries()}
    if not entries:
        return
    if root_attribute(folder) is not None or _creation(folder, entries):
        own = own_names(folder)
        refuse_links(folder, [n for n, kind in entries.items() if kind == "link" and
                              (n in (ROOT, LOCK) or n in own)])
        return
    which = "replace=True replaces a simloader store only; " if replace else ""
    raise NotAStore(f"path: {folder.path!r} is a folder that is not a simloader store (it "
                    f"holds {_listed(list(entries))}); {which}a store is written into a new "
                    f"or empty folder, or into a store simloader made: pass another path")


def _creation(folder: StoreFolder, entries: dict[str, str]) -> bool:
    """What a killed creation leaves before the root: the lock (empty, or naming a simloader
    job) and `provenance/` holding the slots' array only."""
    if not set(entries) <= _CREATION:
        return False
    if LOCK in entries:
        if entries[LOCK] != "file":
            return False
        from simloader.store.lock import holder
        try:
            text = folder.read(LOCK, 4096)
        except (OSError, ValueError):
            return False
        if text.strip() and holder(folder) is None:
            return False
    if "provenance" in entries:
        if entries["provenance"] != "folder":
            return False
        # the slots' array, and the models kept for rendering on read (`pixels.MODELS`)
        return all(n in (ROOT, "written", "models") or LEFTOVER.search(n)
                   for n, _, _ in folder.entries("provenance"))
    return True


def refuse_links(folder: StoreFolder, names: list[str]) -> None:
    """Refuses links among the store's entries `names` (the survey under the lock checks
    every folder below them)."""
    if names:
        raise NotAStore(f"path: the store at {folder.path!r} holds links ({_listed(names)}), "
                        f"which simloader never writes: one could make the writer write or "
                        f"empty a file outside the store; remove them (or write to another "
                        f"path)")


def own_names(folder: StoreFolder) -> set[str]:
    """The store's own top-level folders (see the module's docstring): `provenance`, a
    mixture store's `tasks`, the top folders of the arrays its checksums' record names, and
    the folders holding only arrays and groups simloader writes. Links are not among them
    (the caller refuses those)."""
    folders = {name for name, kind, _ in folder.entries() if kind == "folder"}
    out = {"provenance"} & folders
    attribute = root_attribute(folder)
    if attribute is not None and attribute.get("kind") == "mixture":
        out |= {"tasks"} & folders
    try:
        checks = folder.read_json(CHECKSUM + "/" + ROOT)
    except (OSError, DamagedStore):
        checks = None
    arrays = ((checks or {}).get("attributes") or {}).get("arrays") \
        if isinstance(checks, dict) else None
    if isinstance(arrays, list):
        out.update(a.split("/")[0] for a in arrays if isinstance(a, str) and
                   a.split("/")[0] in folders)
    out.update(name for name in folders - out if _written_by_simloader(folder, name, 0))
    return out


def _written_by_simloader(folder: StoreFolder, name: str, depth: int) -> bool:
    """Folder `name` is an array simloader wrote (its `zarr.json` names the batch key) or a
    group of such arrays (a `zarr.json` of a group without attributes, and nothing else)."""
    try:
        meta = folder.read_json(name + "/" + ROOT)
        entries = folder.entries(name)
    except (OSError, ValueError):
        return False
    if not isinstance(meta, dict):
        return False
    attributes = meta.get("attributes")
    if meta.get("node_type") == "array":
        return isinstance(attributes, dict) and isinstance(attributes.get("key"), str)
    if meta.get("node_type") != "group" or attributes or depth >= _GROUP_DEPTH:
        return False
    return all(entry == ROOT or LEFTOVER.search(entry) or
               (what == "folder" and _written_by_simloader(folder, f"{name}/{entry}", depth + 1))
               for entry, what, _ in entries)


def own_entries(folder: StoreFolder) -> list[tuple[str, str]]:
    """(name, kind) of the store's own top-level entries (its root, groups, arrays, and the
    killed writers' temporary files beside them), its lock aside."""
    own = own_names(folder)
    return [(name, kind) for name, kind, _ in folder.entries()
            if name != LOCK and (name == ROOT or LEFTOVER.search(name) or name in own)]


# the root attribute's key that marks a replace under way (see `clear`)
REPLACING = "replacing"


def clear(folder: StoreFolder) -> None:
    """`replace=True`: removes the store's own entries (never following a link; the lock,
    which the caller holds, and entries the store did not make stay).

    The root is first rewritten (atomically) as a mark of a replace under way, with an
    identity of its own: readers opened before say the store was replaced, a new reader and
    a resuming write are told that a replace stopped part-way, and a replace that fails
    midway (a folder it may not empty, a full disk) leaves a store `replace=True` recognizes
    and finishes. The mark goes last."""
    folder.write_json(ROOT, {"zarr_format": 3, "node_type": "group", "attributes": {
        ATTRIBUTE: {"format": FORMAT, REPLACING: True, "id": new_identity()}}}, durable=True)
    for name, kind in own_entries(folder):
        if name == ROOT:
            continue
        if kind == "folder":
            folder.remove_tree(name)
        else:
            folder.unlink(name)
    folder.unlink(ROOT)
    folder.sync([""])


def replacing(path: str) -> str:
    """What a store whose replace stopped part-way is told, for readers and writers."""
    return (f"path: a replace=True of the store at {path!r} stopped part-way (some of its "
            f"arrays are removed): write with replace=True again to finish it, or remove the "
            f"folder")


def os_error_message(number: Optional[int], stage: str = "writing") -> str:
    """What a failed write (of error number `number`) left, said truly, by `stage`: "opening"
    (before the store's root was written or a replace began: nothing of a store was
    changed), "replacing" (`clear` under way, or done and no new root written yet), else
    "writing" (the committed slots stay)."""
    if number in (errno.EROFS, errno.EACCES, errno.EPERM) and stage == "opening":
        return "simloader cannot write there; nothing was changed by this write"
    if stage == "replacing":
        return ("the replace stopped part-way, so the store there is no longer readable: "
                "write with replace=True again to finish it")
    if number == errno.ENAMETOOLONG:
        return "a name is longer than the file system allows; nothing was written under it"
    if stage == "opening":
        return "no store was written there"
    if number in (errno.EROFS, errno.EACCES, errno.EPERM):
        return ("simloader cannot write there; the store stays readable with the batches "
                "completed so far")
    return ("the store stays readable with the batches completed so far, and calling write "
            "again resumes after them")
