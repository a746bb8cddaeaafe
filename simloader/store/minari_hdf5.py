"""A Minari dataset's HDF5 files, never modified in place (`simloader.store.minari`, "How it
is written"): the empty dataset created marked incomplete under a temporary folder and renamed
into place; each batch's episodes committed whole as a file of their own (written under a
temporary name, fsync'd, renamed), pruned when a write resumes; Minari's
``main_data.hdf5`` assembled from them once all are committed. The free space is checked
before each HDF5 write: HDF5 can crash the process when the disk fills under it."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
import uuid
import warnings
from typing import Any, Optional

from simloader.atomic import PARTIAL, fsync_file, sync_directories
from simloader.store.minari_episodes import EPISODE_FLAGS, episodes
from simloader.store.minari_folder import (BACKUP, CREATING, EPISODES, MAIN, MERGING, METADATA,
                                           datasets_root, read_json, root_of)
from simloader.store.minari_metadata import (atomic_json, incomplete_version, put_metadata,
                                             read_metadata)

# create_dataset_from_buffers warns for each piece of provenance it is not given (author, permalink,
# eval env, env spec); simloader's provenance is in the metadata, so these are noise here.
_NOISE = (r"`code_permalink` is set to None", r"`author` is set to None",
          r"`author_email` is set to None", r"`eval_env` is set to None",
          r"env_spec is None", r"`description` is set to None",
          r"`algorithm_name` is set to None")
_BATCH_RE = re.compile(r"(\d{12})-(\d{12})\.hdf5")


def create_empty(minari: Any, dataset_id: str, dataset_dir: str, description: str,
                 total_episodes: int, metadata: Optional[dict], observation_space: Any,
                 action_space: Any) -> None:
    """Creates the empty dataset, marked incomplete, at ``dataset_dir`` (which exists: it
    holds the lock).

    Minari writes it unmarked; it is made (and marked) under a hidden temporary root inside
    ``dataset_dir`` and its ``data/`` then renamed into place, so that a kill at any moment
    leaves either no ``data/`` or a marked one (and a ``.simloader-creating-*`` folder that the
    next write removes)."""
    from minari.namespace import create_namespace, list_local_namespaces
    from minari.dataset.minari_dataset import parse_dataset_id

    root = root_of(dataset_dir, dataset_id)
    namespace = parse_dataset_id(dataset_id)[0]
    if namespace is not None:
        with datasets_root(root):
            if namespace not in list_local_namespaces():
                create_namespace(namespace)
    os.makedirs(dataset_dir, exist_ok=True)
    staging = tempfile.mkdtemp(prefix=CREATING, dir=dataset_dir)
    try:
        try:
            with datasets_root(staging), warnings.catch_warnings():
                for message in _NOISE:
                    warnings.filterwarnings("ignore", message=message, category=UserWarning)
                # Created empty: the list argument would otherwise hold every episode at once.
                minari.create_dataset_from_buffers(
                    dataset_id, [], env=None, observation_space=observation_space,
                    action_space=action_space, algorithm_name="simloader",
                    description=description, data_format="hdf5")
        except ImportError as e:
            raise ImportError("Minari's 'hdf5' data format needs h5py: pip install h5py") from e
        staged = os.path.join(staging, dataset_id, "data")
        raw = read_json(os.path.join(staged, METADATA))
        assert raw is not None
        raw["simloader"] = {**(metadata or {}), "complete": False, "episodes_written": 0,
                            "total_episodes": total_episodes,
                            "minari_version": raw["minari_version"]}
        raw["minari_version"] = incomplete_version(0, total_episodes)
        atomic_json(os.path.join(staged, METADATA), raw)
        sync_directories([staged])
        # Atomic, and refuses a non-empty data/ (none can be there: the caller holds the lock).
        os.rename(staged, os.path.join(dataset_dir, "data"))
        sync_directories([dataset_dir])
        put_metadata(dataset_dir, raw)  # the backup too
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _need_space(folder: str, need: int, what: str) -> None:
    """Raises OSError(ENOSPC) when the file system of ``folder`` has less than ``need`` bytes
    free for this user: HDF5 may crash the process (not raise) when the disk fills under it."""
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):
        return
    free = st.f_bavail * st.f_frsize
    if free < need:
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} ({what} needs about "
                                    f"{need / 1e6:.1f} MB, {free / 1e6:.1f} MB are free)",
                      folder)


def commit_batch(dataset_dir: str, first: int, batch: dict, n: int) -> None:
    """Commits the first ``n`` trajectories of a checked batch, episodes ``first ..
    first + n - 1``, as ``.simloader-episodes/<first>-<stop>.hdf5``: written under a
    temporary name, fsync'd, renamed (a torn file is never under the committed name)."""
    import h5py
    folder = os.path.join(dataset_dir, EPISODES)
    if not os.path.isdir(folder):
        os.mkdir(folder)
        sync_directories([dataset_dir])
    _need_space(folder, int(1.25 * sum(v[:n].nbytes for v in (
        batch["init"], batch["obs"], batch["control"], batch["diverged"],
        *batch["params"].values()))) + (1 << 20), f"the batch file of episodes {first} to "
        f"{first + n}")
    final = os.path.join(folder, f"{first:012d}-{first + n:012d}.hdf5")
    partial = f"{final}.{uuid.uuid4().hex}{PARTIAL}"
    try:
        with h5py.File(partial, "w") as f:
            for key in ("init", "obs", "control", "diverged",
                        *(k for k in EPISODE_FLAGS if k in batch)):
                f.create_dataset(key, data=batch[key][:n])
            for key, value in batch["params"].items():
                f.create_dataset(f"params/{key}", data=value[:n])
        fsync_file(partial)
        os.replace(partial, final)
        sync_directories([folder])
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise


def committed(dataset_dir: str) -> list[tuple[int, int, str]]:
    """The committed batch files, ``(first, stop, path)``, sorted (read from the names, no
    file opened)."""
    folder = os.path.join(dataset_dir, EPISODES)
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    found = [(int(m.group(1)), int(m.group(2)), os.path.join(folder, name))
             for name in names for m in [_BATCH_RE.fullmatch(name)] if m]
    return sorted(found)


def covered(batches: list[tuple[int, int, str]]) -> int:
    """How many episodes from 0 the batch files hold without a gap."""
    end = 0
    for first, stop, _ in batches:
        if first != end:
            break
        end = stop
    return end


def prune(dataset_dir: str, keep: int, where: str, fix: str) -> None:
    """Resuming: deletes the batch files from episode ``keep`` on (committed after the last
    recorded count), and checks that those before it hold episodes ``0 .. keep - 1``."""
    kept = []
    for first, stop, path in committed(dataset_dir):
        if first >= keep:
            os.unlink(path)
        else:
            kept.append((first, stop, path))
    if covered(kept) != keep or any(stop > keep for _, stop, _ in kept):
        raise ValueError(f"{where}: the incomplete Minari dataset at {dataset_dir} cannot be "
                         f"resumed: its metadata records {keep} episodes written but its "
                         f"{EPISODES}/ holds committed batch files for episodes 0 to "
                         f"{covered(kept)} without a gap (written by a simloader that "
                         f"appended to {MAIN} in place, or edited); {fix}")


def _read_batch(path: str) -> dict:
    import h5py
    with h5py.File(path, "r") as f:
        batch = {key: f[key][()] for key in ("init", "obs", "control", "diverged",
                                             *EPISODE_FLAGS) if key in f}
        batch["params"] = ({key: value[()] for key, value in f["params"].items()}
                           if "params" in f else {})
    return batch


def finish(dataset_dir: str, total: int) -> None:
    """Assembles Minari's ``main_data.hdf5`` from the committed batch files (in
    ``.simloader-merging/``, fsync'd, renamed over ``data/main_data.hdf5``), sets Minari's
    counts, marks the dataset complete and removes the batch files. Interrupted, it leaves
    the batch files: the next write assembles again."""
    from minari.dataset.minari_storage import MinariStorage

    batches = committed(dataset_dir)
    if covered(batches) != total or batches[-1][1] != total:
        raise ValueError(f"path: expected committed batch files for episodes 0 to {total} in "
                         f"{os.path.join(dataset_dir, EPISODES)}, found them up to "
                         f"{covered(batches)}")
    data_dir = os.path.join(dataset_dir, "data")
    scratch = os.path.join(dataset_dir, MERGING)
    shutil.rmtree(scratch, ignore_errors=True)
    os.mkdir(scratch)
    try:
        raw = read_metadata(dataset_dir)
        atomic_json(os.path.join(scratch, METADATA),
                    {**raw, "total_episodes": 0, "total_steps": 0})
        open(os.path.join(scratch, MAIN), "wb").close()
        storage = MinariStorage.read(scratch)  # plain Minari: its metadata here is scratch
        main, written = os.path.join(scratch, MAIN), 0
        for first, stop, path in batches:
            # HDF5 can crash the process when the disk fills under it: refuse beforehand
            # what would not fit (Minari's layout is several times the batch files: measured
            # on what is assembled so far, a guess for the first batch)
            per_episode = (os.path.getsize(main) / written if written else
                           16 * os.path.getsize(path) / (stop - first) + 4096)
            _need_space(scratch, int(1.25 * per_episode * (stop - first)) + (1 << 20),
                        f"assembling {MAIN}" + (f" (about {per_episode * total / 1e6:.1f} "
                                                 f"MB in all)" if written else ""))
            storage.update_episodes(list(episodes(_read_batch(path), stop - first)))
            written += stop - first
        counts = read_json(os.path.join(scratch, METADATA)) or {}
        fsync_file(os.path.join(scratch, MAIN))
        os.replace(os.path.join(scratch, MAIN), os.path.join(data_dir, MAIN))
        sync_directories([data_dir])
        raw = read_metadata(dataset_dir)
        raw.update({k: counts[k] for k in ("total_episodes", "total_steps", "dataset_size")
                    if k in counts})
        state = raw["simloader"]
        state.update(episodes_written=total, complete=True)
        raw["minari_version"] = state["minari_version"]
        put_metadata(dataset_dir, raw)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    shutil.rmtree(os.path.join(dataset_dir, EPISODES), ignore_errors=True)
    with contextlib.suppress(OSError):
        os.remove(os.path.join(dataset_dir, BACKUP))  # complete: nothing left to recover


def hdf5_episodes(data_dir: str) -> Optional[int]:
    """The number of ``episode_*`` groups in the HDF5 file (None: it cannot be opened now)."""
    import h5py
    try:
        # Without a lock: a shared lock held here would make a writer's open for writing fail.
        with h5py.File(os.path.join(data_dir, MAIN), "r", locking=False) as f:
            return sum(1 for k in f.keys() if k.startswith("episode_"))
    except (OSError, ValueError, KeyError, RuntimeError):
        return None
