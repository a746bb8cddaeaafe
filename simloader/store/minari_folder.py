"""A Minari dataset's directory (`simloader.store.minari`): what is there, its lock, what
killed writers left, and its removal; Minari's datasets root.

What is removed, and what never is: only a Minari dataset (a directory holding
``data/metadata.json`` written by Minari, or ``data/main_data.hdf5``): its ``data/`` and
simloader's own entries beside it (the names below); anything else at the path is refused,
naming it, before anything is written there. The lock (``simloader.store.lock``) is held on
``<dataset dir>/simloader.lock``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import threading
from typing import Iterator, Optional

from simloader.atomic import PARTIAL, sync_directories
from simloader.store import lock as store_lock

# Minari finds its root only through the MINARI_DATASETS_PATH environment variable; writing to a
# caller-given root means setting it for the duration of the dataset's creation. The lock keeps
# two threads of this process from interleaving their set/restore.
_ENV_LOCK = threading.Lock()

METADATA = "metadata.json"            # Minari's metadata file, in <dataset dir>/data/
BACKUP = ".simloader-metadata.json"   # the last marked metadata, in <dataset dir>/
MAIN = "main_data.hdf5"               # Minari's HDF5 file, in <dataset dir>/data/
EPISODES = ".simloader-episodes"      # the committed batch files, in <dataset dir>/
MERGING = ".simloader-merging"        # where main_data.hdf5 is assembled, in <dataset dir>/
CREATING = ".simloader-creating-"     # tempfile.mkdtemp's prefix of a creation's folder
# exactly what mkdtemp makes of that prefix: 8 characters of tempfile's alphabet
_CREATING_RE = re.compile(re.escape(CREATING) + r"[a-z0-9_]{8}")
_BACKUP_PARTIAL_RE = re.compile(re.escape(BACKUP) + r"\.[0-9a-f]{32}" + re.escape(PARTIAL))
_OWN = (store_lock.FILE, BACKUP, EPISODES, MERGING)  # simloader's entries of a dataset dir


@contextlib.contextmanager
def datasets_root(path: Optional[str | os.PathLike]) -> Iterator[None]:
    """Point Minari at ``path`` as its datasets root while inside (no-op for None)."""
    if path is None:
        yield
        return
    with _ENV_LOCK:
        old = os.environ.get("MINARI_DATASETS_PATH")
        os.environ["MINARI_DATASETS_PATH"] = os.path.abspath(os.fspath(path))
        try:
            yield
        finally:
            if old is None:
                del os.environ["MINARI_DATASETS_PATH"]
            else:
                os.environ["MINARI_DATASETS_PATH"] = old


def dataset_dir_of(path: Optional[str | os.PathLike], dataset_id: str) -> str:
    with datasets_root(path):
        from minari.storage import get_dataset_path
        return os.path.abspath(os.fspath(get_dataset_path(dataset_id)))


def root_of(dataset_dir: str, dataset_id: str) -> str:
    root = dataset_dir
    for _ in dataset_id.split("/"):  # <root>/<namespace>/.../<name>
        root = os.path.dirname(root)
    return root


def _real_dir(path: str) -> bool:
    return os.path.isdir(path) and not os.path.islink(path)


def _own(name: str) -> bool:
    """An entry simloader puts in a dataset directory (besides Minari's ``data/``)."""
    return (name in _OWN or _CREATING_RE.fullmatch(name) is not None
            or _BACKUP_PARTIAL_RE.fullmatch(name) is not None)


def _listing(folder: str, names: list[str], limit: int = 8) -> str:
    shown = [n + ("/" if os.path.isdir(os.path.join(folder, n))
                  and not os.path.islink(os.path.join(folder, n)) else "")
             for n in names[:limit]]
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return f"{shown}{more}"


def read_json(where: str) -> Optional[dict]:
    try:
        with open(where) as f:
            out = json.load(f)
    except (OSError, ValueError):
        return None
    return out if isinstance(out, dict) else None


def _is_minari_metadata(raw: Optional[dict]) -> bool:
    return raw is not None and "dataset_id" in raw and "minari_version" in raw


def survey(dataset_dir: str, where: str) -> str:
    """What is at the dataset's directory: "absent"; "empty" (nothing but simloader's own
    files: the lock, a killed creation); "dataset" (Minari's ``data/`` with its metadata).
    Anything else is refused, naming it: nothing there is written or removed."""
    keep = ("nothing was written or removed (replace=True removes only a Minari dataset): "
            "write to another path")
    if os.path.islink(dataset_dir):
        raise ValueError(f"{where}: expected a Minari dataset's folder or nothing at "
                         f"{dataset_dir!r}, found a symbolic link (to "
                         f"{os.readlink(dataset_dir)!r}); {keep}")
    if not os.path.lexists(dataset_dir):
        return "absent"
    if not os.path.isdir(dataset_dir):
        raise ValueError(f"{where}: expected a Minari dataset's folder or nothing at "
                         f"{dataset_dir!r}, found a file; {keep}")
    names = sorted(os.listdir(dataset_dir))
    linked = [n for n in names if (n == "data" or _own(n))
              and os.path.islink(os.path.join(dataset_dir, n))]
    if linked:
        raise ValueError(f"{where}: expected the Minari dataset's folder {dataset_dir!r} to "
                         f"hold its own files, found symbolic link(s) {linked} where "
                         f"simloader and Minari put theirs; {keep}")
    data = os.path.join(dataset_dir, "data")
    if os.path.isdir(data) and (
            _is_minari_metadata(read_json(os.path.join(data, METADATA)))
            or _is_minari_metadata(read_json(os.path.join(dataset_dir, BACKUP)))
            or os.path.isfile(os.path.join(data, MAIN))):  # its metadata cut short
        return "dataset"
    other = [n for n in names if not _own(n)]
    if not other:
        return "empty"
    said = (" (its data/ holds no Minari metadata.json)" if "data" in other else "")
    raise ValueError(f"{where}: expected a Minari dataset (a folder holding "
                     f"data/{METADATA} written by Minari) or nothing at {dataset_dir!r}, "
                     f"found a folder holding {_listing(dataset_dir, names)}{said}, which is "
                     f"not a Minari dataset; {keep}")


@contextlib.contextmanager
def locked(dataset_dir: str, dataset_id: str) -> Iterator[store_lock.WriterLock]:
    """Holds the dataset's lock (``<dataset dir>/simloader.lock``) while inside, after
    removing what killed writers of this dataset left (they cannot be running now)."""
    os.makedirs(dataset_dir, exist_ok=True)
    held = store_lock.WriterLock(dataset_dir, store_lock.new_job_id()).acquire()
    try:
        _remove_leftovers(dataset_dir, dataset_id)
        yield held
    finally:
        held.release()


def _remove_leftovers(dataset_dir: str, dataset_id: str) -> None:
    """Under the lock: killed creations' folders of this dataset (``.simloader-creating-`` and
    mkdtemp's 8 characters, real directories only: in the dataset's directory, and in the
    datasets root where earlier versions made them, there only when they hold this dataset's
    id and nothing else), an interrupted assembly, and partial batch files."""
    for name in os.listdir(dataset_dir):
        entry = os.path.join(dataset_dir, name)
        if (_CREATING_RE.fullmatch(name) or name == MERGING) and _real_dir(entry):
            shutil.rmtree(entry)
        elif _BACKUP_PARTIAL_RE.fullmatch(name) and not os.path.islink(entry):
            os.unlink(entry)
    root = root_of(dataset_dir, dataset_id)
    first = dataset_id.split("/")[0]
    with contextlib.suppress(OSError):
        for name in os.listdir(root):
            staging = os.path.join(root, name)
            if not (_CREATING_RE.fullmatch(name) and _real_dir(staging)):
                continue
            with contextlib.suppress(OSError):
                if os.listdir(staging) == [first] and _real_dir(
                        os.path.join(staging, dataset_id)):
                    shutil.rmtree(staging)
    episodes = os.path.join(dataset_dir, EPISODES)
    if _real_dir(episodes):
        for name in os.listdir(episodes):
            if name.endswith(PARTIAL):
                os.unlink(os.path.join(episodes, name))


def clear(dataset_dir: str) -> None:
    """Removes the dataset (its ``data/`` and simloader's files) but not the lock, which this
    process holds, nor anything else in the directory. Symbolic links are removed, never
    followed."""
    for name in os.listdir(dataset_dir):
        if name == store_lock.FILE or not (name == "data" or _own(name)):
            continue
        entry = os.path.join(dataset_dir, name)
        if _real_dir(entry):
            shutil.rmtree(entry)
        else:
            os.unlink(entry)
    sync_directories([dataset_dir])
