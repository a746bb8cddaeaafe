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
store's own entries are its root `zarr.json`, its lock, and the folders that hold a
`zarr.json` (its groups and arrays); `replace=True` removes those and leaves any other entry a
user put beside them. A link anywhere among them is refused before the lock is taken: a lock or
a folder that links outside the store would have the writer empty or write a file that is not
its own.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from simloader.atomic import PARTIAL, sync_directories
from simloader.store.lock import FILE as LOCK
from simloader.store.zarr_format import ATTRIBUTE

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


class NotAStore(ValueError):
    """`write`'s path is not one a store may be written to (a folder of the user's, a system
    folder, a file); nothing was written or deleted."""


def system_folder(path: str) -> bool:
    """`path` (resolved) is a system folder or the home folder, or lies in a kernel's one."""
    real = os.path.realpath(path)
    home = os.path.realpath(os.path.expanduser("~"))
    return (real in _SYSTEM or real == home or
            any(real.startswith(top + "/") for top in _NEVER_BELOW))


def is_store_root(path: str) -> bool:
    """`path` holds a root `zarr.json` (a file, not a link) with the `simloader` attribute."""
    root = os.path.join(path, ROOT)
    try:
        if not stat.S_ISREG(os.lstat(root).st_mode):
            return False
        with open(root, encoding="utf-8") as f:
            meta = json.load(f)
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(meta, dict) and isinstance(meta.get("attributes"), dict) and \
        ATTRIBUTE in meta["attributes"]


def _listed(names: list[str]) -> str:
    names = sorted(names)
    shown = ", ".join(repr(n) for n in names[:_SHOWN])
    return shown + (f" and {len(names) - _SHOWN} more" if len(names) > _SHOWN else "")


def check_target(path: str, replace: bool) -> None:
    """Refuses (`NotAStore`) a path a store may not be written to, before anything is made;
    see the module's docstring. Reads only."""
    if path == "":
        raise NotAStore("path: expected the folder of a store, got an empty path")
    if system_folder(path):
        raise NotAStore(f"path: {path!r} is a system folder ({os.path.realpath(path)}); a "
                        f"store is written into a folder of its own: pass a new folder, e.g. "
                        f"{os.path.join(path, 'trajectories.zarr')!r}")
    if not os.path.lexists(path):
        return
    if not os.path.isdir(path):
        raise NotAStore(f"path: {path!r} is a file, not a folder; a store is a folder: pass a "
                        f"new path")
    entries = os.listdir(path)
    if not entries:
        return
    if is_store_root(path) or _creation(path, entries):
        refuse_links(path, [e for e in entries if e == ROOT or e == LOCK or
                            own_folder(os.path.join(path, e))])
        return
    which = "replace=True replaces a simloader store only; " if replace else ""
    raise NotAStore(f"path: {path!r} is a folder that is not a simloader store (it holds "
                    f"{_listed(entries)}); {which}a store is written into a new or empty "
                    f"folder, or into a store simloader made: pass another path")


def _creation(path: str, entries: list[str]) -> bool:
    """What a killed creation leaves before the root: the lock (empty, or naming a simloader
    job) and `provenance/` holding the slots' array only."""
    if not set(entries) <= _CREATION:
        return False
    if LOCK in entries:
        lock = os.path.join(path, LOCK)
        try:
            if os.path.islink(lock) or not os.path.isfile(lock):
                return False
            with open(lock, encoding="utf-8") as f:
                text = f.read(4096)
            if text.strip() and "job" not in json.loads(text):
                return False
        except (OSError, ValueError, TypeError, UnicodeDecodeError):
            return False
    folder = os.path.join(path, "provenance")
    if "provenance" in entries:
        if os.path.islink(folder) or not os.path.isdir(folder):
            return False
        # the slots' array, and the models kept for rendering on read (`pixels.MODELS`)
        return all(n in (ROOT, "written", "models") or LEFTOVER.search(n)
                   for n in os.listdir(folder))
    return True


def own_folder(path: str) -> bool:
    """A folder of the store's: a group or an array (it holds a `zarr.json`), or the
    provenance group a killed creation left; links are checked by the caller."""
    return (os.path.isdir(path) and not os.path.islink(path) and
            (os.path.lexists(os.path.join(path, ROOT)) or os.path.basename(path) == "provenance"))


def refuse_links(root: str, names: list[str]) -> None:
    """Refuses links among the store's top-level entries `names` (the survey under the lock
    checks every folder below them)."""
    links = [n for n in names if os.path.islink(os.path.join(root, n))]
    if links:
        raise NotAStore(f"path: the store at {root!r} holds links ({_listed(links)}), which "
                        f"simloader never writes: one could make the writer write or empty a "
                        f"file outside the store; remove them (or write to another path)")


def own_entries(root: str) -> list[str]:
    """The store's own top-level entries (its root, groups, arrays, and the killed writers'
    temporary files beside them), its lock aside."""
    out = []
    for entry in os.scandir(root):
        if entry.name == LOCK:
            continue
        if entry.name == ROOT or LEFTOVER.search(entry.name) or own_folder(entry.path):
            out.append(entry.path)
    return out


def clear(root: str) -> None:
    """`replace=True`: removes the store's own entries (never following a link; the lock,
    which the caller holds, and entries the store did not make stay)."""
    for path in own_entries(root):
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        else:
            os.unlink(path)
    sync_directories([root])
