"""Write simulated trajectories as a Minari dataset (offline-RL format), streamed batch by batch.

    from simloader.store.minari import write_minari
    ds = simloader.SimDataset("cartpole", nbatch=256, nstep=200, num_batches=40,
                              control=simloader.controls.Uniform())
    batches = ({k: v.numpy() for k, v in b.items()} for b in ds)
    write_minari(batches, "datasets", dataset_id="simloader/cartpole/uniform-v0",
                 total_episodes=256 * 40)
    # later, with MINARI_DATASETS_PATH=datasets:
    minari.load_dataset("simloader/cartpole/uniform-v0")

Where the dataset goes
    ``path`` is a Minari *datasets root*: the directory Minari reads ``MINARI_DATASETS_PATH`` from
    (``minari.storage.get_dataset_path``; without the variable Minari uses ``~/.minari/datasets``).
    The dataset is written to ``<path>/<dataset_id>/data/`` and that dataset directory
    ``<path>/<dataset_id>`` is returned. ``path=None`` means Minari's own root (the environment
    variable, or its default). ``minari.load_dataset(dataset_id)`` finds the dataset when
    ``MINARI_DATASETS_PATH`` names the same ``path``; ``minari.MinariDataset(<returned dir>/data)``
    opens it without the variable. The id must end in a version ``-v<N>`` (Minari's ids do);
    one without is refused before anything is written or removed. ``write_minari`` never
    overwrites an existing dataset of that id; ``write`` (``simloader.write(...,
    format="minari")``) resumes an interrupted one of the same configuration, and overwrites
    only with ``replace=True``.

What is removed, and what never is
    Only a Minari dataset is ever removed or overwritten: a dataset directory holding
    ``data/metadata.json`` written by Minari, or ``data/main_data.hdf5`` (its ``data/`` and
    simloader's own files beside it are removed; any other file in that directory is left
    alone). A path that exists but is not one (a
    file, a symbolic link, a folder of other things) is refused with a ValueError naming it and
    what it holds, with or without ``replace=True``, before anything is written there.

One writer at a time
    ``write`` and ``write_minari`` hold ``simloader.store.lock.WriterLock`` on
    ``<dataset dir>/simloader.lock`` (an ``flock``) from before they look at the dataset to
    their return. A second writer of the same dataset is refused at once with
    ``simloader.store.lock.StoreLocked`` naming the holder (host, process, start time);
    ``replace=True`` does not bypass it. A killed writer's lock is released by the kernel. The
    lock file stays in the dataset directory (Minari ignores it); a directory holding only
    simloader's own files (the lock, a killed creation) counts as no dataset.

How a batch maps to episodes (one trajectory = one episode)
    observations  ``initial_state[i]`` followed by the ``nstep`` rows of
                  ``batch[observation_key][i]`` (the observation after each step):
                  ``nstep + 1`` rows, as Minari expects.
    actions       ``control[i]``: ``nstep`` rows, row t applied before step t.
    rewards       zeros (simloader simulates no task, so there is no reward to record).
    terminations  False, except True at the last step of a trajectory flagged ``diverged`` (the
                  simulation became unstable: its later states are not a valid continuation).
    truncations   True at the last step of a trajectory that did not diverge (it only stopped
                  because the rollout was ``nstep`` long), False elsewhere.
    infos         the randomized values the trajectory ran with: ``batch["params"][key][i]``
                  as ``episode.infos["params"][key]`` (``"/"`` in a key written ``"|"``),
                  repeated on each of the ``nstep + 1`` rows (Minari's infos are per step,
                  the reset's row first; the values do not change within an episode), e.g.
                  ``ep.infos["params"]["body_mass"][0]`` is the trajectory's ``body_mass``
                  row (``"variant"`` for ``dr.Variants``). Without ``params``, ``{}``.
                  The initial state is ``ep.observations[0]``.
    Other keys of a batch (sensordata, ...) are not stored.
    observation_space: ``gymnasium.spaces.Box(-inf, inf, (nobs,), dtype)`` of the first batch.
    action_space: ``Box(low, high, (nact,), dtype)``; ``write_minari`` takes ``action_bounds``
    (default unbounded); ``write`` gives the range MuJoCo clamps each control column to
    (``simloader.controls.applied_bounds``): ``actuator_ctrlrange`` for the ``ctrl`` columns of
    actuators with ``actuator_ctrllimited`` (unless the model disables clamping; the widest
    over the models of ``models=`` / ``dr.Variants``; unbounded for actuators whose
    ``actuator_ctrlrange`` is randomized), and unbounded for the other columns of
    ``control_spec`` (``qfrc_applied``, ``xfrc_applied``, ...) and unlimited actuators.
    Recorded actions are the requested controls: one beyond the range (MuJoCo clamped it)
    can lie outside the Box. No gymnasium environment is recorded (``env_spec`` is None).

Metadata
    ``metadata`` (JSON-able dict: config description, fingerprint, versions, ...) is stored
    under the key ``"simloader"`` of the dataset's ``data/metadata.json``:
    ``minari.load_dataset(id).storage.metadata["simloader"]``, together with the write's
    progress record (the keys ``PROGRESS_KEYS``, which ``metadata`` must not use):
    ``"complete"`` (bool), ``"episodes_written"`` (episodes durably committed),
    ``"total_episodes"`` (the target) and ``"minari_version"`` (the Minari that created it).
    Minari's own ``description`` is ``metadata["description"]`` when that is a string, else a
    one-line summary. ``algorithm_name`` is ``"simloader"``.

How it is written: no torn HDF5 file, whatever stops the write
    HDF5 is not crash-safe: a file appended in place and cut by a kill or a full disk can be
    unreadable (h5py: "addr overflow", "truncated file"), or crash the process that opens it.
    So no HDF5 file is ever modified in place:

    * Each batch's episodes are written to a file of their own under a temporary name
      (``<dataset dir>/.simloader-episodes/<first>-<stop>.hdf5.<random>.partial``), fsync'd
      and renamed to ``<first>-<stop>.hdf5``: a committed batch file is whole. Then the
      progress record counts it.
    * Once every batch is committed, Minari's ``data/main_data.hdf5`` is assembled from them
      (through Minari's own ``update_episodes``) in ``<dataset dir>/.simloader-merging/``,
      fsync'd and renamed over the empty ``data/main_data.hdf5`` that Minari created; then
      Minari's counts are set, the dataset is marked complete and the batch files removed.
    * ``metadata.json`` is always replaced atomically (temporary file, fsync, rename); the last
      metadata is also kept in ``<dataset dir>/.simloader-metadata.json`` (removed when
      complete) and read from there if ``metadata.json`` is unreadable all the same.
    * The dataset is created empty by Minari in ``<dataset dir>/.simloader-creating-<random>/``
      and its ``data/`` renamed into place once marked incomplete, so no unmarked dataset ever
      appears at the path. The next write of that dataset removes such a folder left by a
      killed creation (only folders of exactly that pattern: in the dataset's directory, or,
      as earlier simloader versions made them, in the datasets root holding this dataset's id
      and nothing else).

An interrupted write, and how loading one says so
    A process killed mid-write (SIGKILL, power loss), or stopped by an exception (Ctrl-C, a
    full disk: ``write`` raises OSError saying the dataset stays resumable), leaves the dataset
    incomplete, marked so from its creation to its last step:

    * ``"complete": False`` and ``"episodes_written"`` in the ``"simloader"`` metadata,
      updated after each batch file is committed (so the recorded count never exceeds what
      is committed; there may be one batch file more, the batch in flight).
    * Minari's ``minari_version`` metadata holds ``INCOMPLETE_MARK`` (followed by the counts)
      instead of a version. Minari validates this key when it opens a dataset:
      ``minari.load_dataset(id)`` and ``minari.MinariDataset(dir)`` raise ValueError
      "... does not support the dataset generated by Minari simloader-incomplete: 128 of 384
      episodes written; ...", which names the state and the way out. The real version is
      restored when the dataset is complete. (``list_local_datasets`` lists it, with that
      version; with ``compatible_minari_version=True`` it leaves it out.) Minari offers no
      hook for a dataset to warn on load, and this refusal is the only check it makes of a
      dataset's metadata, so it is the one clean way to keep a half dataset from being
      trained on as if whole, without patching Minari.
    * ``status(path)`` reports it (complete or not, episodes recorded, committed, target).

    ``simloader.write(dataset, path, batches=, format="minari")`` at a path holding an
    incomplete dataset of the same fingerprint (and simulator versions) resumes it: batch files
    beyond ``episodes_written`` and partial files are deleted, and the stream continues at
    batch ``episodes_written // nbatch``; the stream is deterministic, so the result equals an
    uninterrupted write episode by episode. A complete dataset, one of another configuration,
    or one without simloader's progress record is refused (ValueError) unless
    ``replace=True``, which removes it (``data/`` and simloader's files) and writes afresh. An
    incomplete dataset of a simloader that appended to ``main_data.hdf5`` in place has no
    batch files and cannot be resumed (ValueError; ``replace=True``). ``write_minari`` (the
    lower-level function taking any iterable of batches) does not resume: it refuses an
    existing id and removes what it wrote when it raises.

Memory and disk
    Only the batch being written is held in memory (and one batch file's episodes while
    assembling). Disk: the batch files (compact: the arrays as they are) and, at the end,
    ``main_data.hdf5`` beside them (Minari's layout, several times larger for short
    episodes) until the batch files are removed. HDF5 can crash the process when the disk
    fills under it, so the free space is checked before each batch file and each step of the
    assembly (an estimate from what is written so far), and a shortfall raised as
    OSError(ENOSPC) naming what is needed; writing again once there is room resumes. Minari's
    "hdf5" data format needs the package ``h5py``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import tempfile
import threading
import uuid
import warnings
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional

import numpy as np

from simloader import sharding
from simloader.atomic import PARTIAL, atomic_write, sync_directories
from simloader.store import lock as store_lock

__all__ = ["write_minari", "write", "status", "INCOMPLETE_MARK", "PROGRESS_KEYS"]

# Minari finds its root only through the MINARI_DATASETS_PATH environment variable; writing to a
# caller-given root means setting it for the duration of the dataset's creation. The lock keeps
# two threads of this process from interleaving their set/restore.
_ENV_LOCK = threading.Lock()

# create_dataset_from_buffers warns for each piece of provenance it is not given (author, permalink,
# eval env, env spec); simloader's provenance is in the metadata, so these are noise here.
_NOISE = (r"`code_permalink` is set to None", r"`author` is set to None",
          r"`author_email` is set to None", r"`eval_env` is set to None",
          r"env_spec is None", r"`description` is set to None",
          r"`algorithm_name` is set to None")

#: What ``minari_version`` starts with while a write is in progress (Minari refuses to open it).
INCOMPLETE_MARK = "simloader-incomplete"
#: The keys of the ``"simloader"`` metadata that record the write's progress.
PROGRESS_KEYS = ("complete", "episodes_written", "total_episodes", "minari_version")

_METADATA = "metadata.json"            # Minari's metadata file, in <dataset dir>/data/
_BACKUP = ".simloader-metadata.json"   # the last marked metadata, in <dataset dir>/
_MAIN = "main_data.hdf5"               # Minari's HDF5 file, in <dataset dir>/data/
_EPISODES = ".simloader-episodes"      # the committed batch files, in <dataset dir>/
_MERGING = ".simloader-merging"        # where main_data.hdf5 is assembled, in <dataset dir>/
_CREATING = ".simloader-creating-"     # tempfile.mkdtemp's prefix of a creation's folder
# exactly what mkdtemp makes of that prefix: 8 characters of tempfile's alphabet
_CREATING_RE = re.compile(re.escape(_CREATING) + r"[a-z0-9_]{8}")
_BATCH_RE = re.compile(r"(\d{12})-(\d{12})\.hdf5")
_BACKUP_PARTIAL_RE = re.compile(re.escape(_BACKUP) + r"\.[0-9a-f]{32}" + re.escape(PARTIAL))
_OWN = (store_lock.FILE, _BACKUP, _EPISODES, _MERGING)  # simloader's entries of a dataset dir


def _import_minari():
    try:
        import minari
        from gymnasium.spaces import Box  # noqa: F401
    except ImportError as e:
        raise ImportError("writing Minari datasets needs minari and gymnasium: "
                          "pip install 'minari>=0.5' h5py") from e
    return minari


def write_minari(batches: Iterable[Mapping[str, Any]], path: Optional[str | os.PathLike], *,
                 dataset_id: str, total_episodes: int, observation_key: str = "state",
                 metadata: Optional[dict] = None,
                 progress: Optional[Callable[[int], Any]] = None,
                 action_bounds: Optional[tuple[Any, Any]] = None) -> str:
    """Writes ``total_episodes`` simulated trajectories from ``batches`` as a Minari dataset.

    Batches are consumed until ``total_episodes`` trajectories are written (the last batch is cut
    if it holds more, and no further batch is drawn, so an endless SimDataset works). While it
    is written the dataset is marked incomplete and locked (see the module docstring); if this
    call raises, what it wrote is removed (the lock file stays).

    Args:
      batches: dicts of numpy arrays with ``initial_state``, ``observation_key``, ``control``
        and ``diverged``, as a SimDataset yields them; and optionally ``params`` (a dict of
        ``(n, ...)`` arrays, stored in each episode's ``infos["params"]``).
      path: the Minari datasets root (None: Minari's own).
      dataset_id: the Minari id ending in a version, e.g. ``"simloader/cartpole-v0"``; must
        not exist yet.
      total_episodes: how many trajectories to write.
      observation_key: the batch key stored as observations.
      metadata: JSON-able dict stored under ``"simloader"`` (without the keys ``PROGRESS_KEYS``).
      progress: called as ``progress(n_episodes_done)`` after each batch.
      action_bounds: ``(low, high)``, each ``(nact,)``: the action space's bounds (default
        unbounded).

    Returns:
      The dataset's directory ``<path>/<dataset_id>``.

    Raises:
      ValueError: fewer trajectories than ``total_episodes``, a malformed batch, a bad argument,
        an existing dataset of that id, or something else at its path.
      StoreLocked: another process is writing that dataset.
    """
    _import_minari()
    _check_id(dataset_id, "dataset_id", "dataset_id")
    total_episodes = _check_args(total_episodes, metadata, progress)
    dataset_dir = _dataset_dir(path, dataset_id)
    where = f"dataset_id: {dataset_id!r}"

    def refuse_existing() -> None:
        raise ValueError(f"dataset_id: expected an id not yet used under the datasets root, "
                         f"but {dataset_id!r} already exists at {dataset_dir}")

    # Checked before any simulation is drawn: Minari would only refuse when creating it.
    if _survey(dataset_dir, where) == "dataset":
        refuse_existing()
    with _locked(dataset_dir, dataset_id):
        if _survey(dataset_dir, where) == "dataset":
            refuse_existing()
        return _write(iter(batches), dataset_id, dataset_dir, total_episodes=total_episodes,
                      observation_key=observation_key, metadata=metadata, progress=progress,
                      done=0, first_index=0, create=True, keep_partial=False,
                      action_bounds=action_bounds)


def _check_id(dataset_id: Any, name: str, what: str) -> None:
    """A Minari dataset id ``(namespace/)name-v<N>``, refused before anything is written."""
    from minari.dataset.minari_dataset import parse_dataset_id
    if not isinstance(dataset_id, str) or not dataset_id:
        raise ValueError(f"{name}: expected a non-empty str such as 'simloader/cartpole-v0', "
                         f"got {dataset_id!r}")
    try:
        version = parse_dataset_id(dataset_id)[2]
    except (ValueError, TypeError):  # Minari: int(None) when the version is missing
        version = None
    if version is None:
        raise ValueError(f"{name}: expected {what} to be a Minari dataset id ending in a "
                         f"version '-v<N>', such as 'cartpole-uniform-v0' (Minari's ids need "
                         f"one), got {dataset_id!r}; nothing was written or removed")


def _check_args(total_episodes: Any, metadata: Any, progress: Any) -> int:
    if isinstance(total_episodes, bool) or not isinstance(total_episodes, (int, np.integer)) \
            or total_episodes < 1:
        raise ValueError(f"total_episodes: expected an int >= 1, got {total_episodes!r}")
    if metadata is not None:
        if not isinstance(metadata, dict):
            raise ValueError(f"metadata: expected a JSON-able dict or None, "
                             f"got {type(metadata).__name__}")
        try:
            json.dumps(metadata)
        except (TypeError, ValueError) as e:
            raise ValueError(f"metadata: expected a JSON-able dict, got one that json cannot "
                             f"write ({e})") from None
        reserved = sorted(set(PROGRESS_KEYS) & set(metadata))
        if reserved:
            raise ValueError(f"metadata: expected none of the keys {list(PROGRESS_KEYS)} "
                             f"(simloader records the write's progress under them), got "
                             f"{reserved}")
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected a callable(n_episodes_done) or None, "
                         f"got {type(progress).__name__}")
    return int(total_episodes)


def _dataset_dir(path: Optional[str | os.PathLike], dataset_id: str) -> str:
    with _datasets_root(path):
        from minari.storage import get_dataset_path
        return os.path.abspath(os.fspath(get_dataset_path(dataset_id)))


# --- what is at the path, the lock, and what a killed writer left ---------------------------

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


def _is_minari_metadata(raw: Optional[dict]) -> bool:
    return raw is not None and "dataset_id" in raw and "minari_version" in raw


def _survey(dataset_dir: str, where: str) -> str:
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
            _is_minari_metadata(_read_json(os.path.join(data, _METADATA)))
            or _is_minari_metadata(_read_json(os.path.join(dataset_dir, _BACKUP)))
            or os.path.isfile(os.path.join(data, _MAIN))):  # its metadata cut short
        return "dataset"
    other = [n for n in names if not _own(n)]
    if not other:
        return "empty"
    said = (" (its data/ holds no Minari metadata.json)" if "data" in other else "")
    raise ValueError(f"{where}: expected a Minari dataset (a folder holding "
                     f"data/{_METADATA} written by Minari) or nothing at {dataset_dir!r}, "
                     f"found a folder holding {_listing(dataset_dir, names)}{said}, which is "
                     f"not a Minari dataset; {keep}")


@contextlib.contextmanager
def _locked(dataset_dir: str, dataset_id: str) -> Iterator[store_lock.WriterLock]:
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
        if (_CREATING_RE.fullmatch(name) or name == _MERGING) and _real_dir(entry):
            shutil.rmtree(entry)
        elif _BACKUP_PARTIAL_RE.fullmatch(name) and not os.path.islink(entry):
            os.unlink(entry)
    root = _root_of(dataset_dir, dataset_id)
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
    episodes = os.path.join(dataset_dir, _EPISODES)
    if _real_dir(episodes):
        for name in os.listdir(episodes):
            if name.endswith(PARTIAL):
                os.unlink(os.path.join(episodes, name))


def _real_dir(path: str) -> bool:
    return os.path.isdir(path) and not os.path.islink(path)


def _root_of(dataset_dir: str, dataset_id: str) -> str:
    root = dataset_dir
    for _ in dataset_id.split("/"):  # <root>/<namespace>/.../<name>
        root = os.path.dirname(root)
    return root


def _clear(dataset_dir: str) -> None:
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


# --- writing ---------------------------------------------------------------------------------

def _write(it: Iterator[Mapping[str, Any]], dataset_id: str, dataset_dir: str, *,
           total_episodes: int, observation_key: str, metadata: Optional[dict],
           progress: Optional[Callable[[int], Any]], done: int, first_index: int,
           create: bool, keep_partial: bool,
           action_bounds: Optional[tuple[Any, Any]] = None) -> str:
    """Creates the dataset (``create``) or continues one holding ``done`` committed episodes,
    from the batches of ``it`` (the first being batch ``first_index`` of the stream), then
    assembles and marks it complete. ``keep_partial``: leave what was written when this raises
    (it can be resumed), else remove it when this call created it. The caller holds the
    lock."""
    minari = _import_minari()
    from gymnasium.spaces import Box

    first = next(it, None)
    if first is None:
        raise ValueError(f"batches: expected at least one batch for {total_episodes} episodes, "
                         f"got an empty iterable")
    first = _check_batch(first, observation_key, first_index, None)
    nobs, nact = first["obs"].shape[2], first["control"].shape[2]
    shapes = (nobs, nact)
    data_dir = os.path.join(dataset_dir, "data")
    try:
        if create:
            description = (metadata or {}).get("description")
            if not isinstance(description, str):
                description = (f"simloader: {total_episodes} simulated trajectories; "
                               f"observations '{observation_key}' ({nobs}), actions 'control' "
                               f"({nact}); no reward")
            _create(minari, dataset_id, dataset_dir, description, total_episodes, metadata,
                    Box(-np.inf, np.inf, (nobs,), first["obs"].dtype),
                    _action_space(action_bounds, nact, first["control"].dtype))
        else:
            from minari.dataset.minari_storage import MinariStorage
            storage = MinariStorage.read(data_dir)
            if storage.observation_space.shape != (nobs,) or \
                    storage.action_space.shape != (nact,):
                raise ValueError(
                    f"batches[{first_index}]: expected (nobs, nact) = "
                    f"{(storage.observation_space.shape[0], storage.action_space.shape[0])} "
                    f"as the dataset at {dataset_dir} holds, got {shapes}")
        batch: Optional[dict] = first
        index = first_index
        while True:
            assert batch is not None
            n = min(batch["obs"].shape[0], total_episodes - done)
            _commit_batch(dataset_dir, done, batch, n)
            done += n
            batch = None  # let this batch go before the next one is simulated
            # After the commit: the recorded count never exceeds what is committed.
            _mark(dataset_dir, episodes_written=done, complete=False)
            if progress is not None:
                progress(done)
            if done >= total_episodes:
                break
            nxt = next(it, None)
            index += 1
            if nxt is None:
                raise ValueError(f"batches: expected {total_episodes} episodes (total_episodes), "
                                 f"but the iterable ended after {done} in "
                                 f"{index - first_index} batches")
            batch = _check_batch(nxt, observation_key, index, shapes)
        _finish(dataset_dir, total_episodes)
    except BaseException:
        if create and not keep_partial:
            # A half-written dataset is marked incomplete, but this caller cannot resume it.
            with contextlib.suppress(OSError):
                _clear(dataset_dir)
        raise
    return dataset_dir


def _action_space(bounds: Optional[tuple[Any, Any]], nact: int, dtype: Any) -> Any:
    from gymnasium.spaces import Box
    if bounds is None:
        return Box(-np.inf, np.inf, (nact,), dtype)
    low, high = (np.asarray(b, dtype=np.float64) for b in bounds)
    if low.shape != (nact,) or high.shape != (nact,) or np.any(low > high):
        raise ValueError(f"action_bounds: expected (low, high) of shape ({nact},) each (the "
                         f"batches' control columns) with low <= high, got shapes "
                         f"{low.shape} and {high.shape}")
    return Box(low.astype(dtype), high.astype(dtype), (nact,), dtype)


def _create(minari: Any, dataset_id: str, dataset_dir: str, description: str,
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

    root = _root_of(dataset_dir, dataset_id)
    namespace = parse_dataset_id(dataset_id)[0]
    if namespace is not None:
        with _datasets_root(root):
            if namespace not in list_local_namespaces():
                create_namespace(namespace)
    os.makedirs(dataset_dir, exist_ok=True)
    staging = tempfile.mkdtemp(prefix=_CREATING, dir=dataset_dir)
    try:
        try:
            with _datasets_root(staging), warnings.catch_warnings():
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
        raw = _read_json(os.path.join(staged, _METADATA))
        assert raw is not None
        raw["simloader"] = {**(metadata or {}), "complete": False, "episodes_written": 0,
                            "total_episodes": total_episodes,
                            "minari_version": raw["minari_version"]}
        raw["minari_version"] = _incomplete_version(0, total_episodes)
        _atomic_json(os.path.join(staged, _METADATA), raw)
        sync_directories([staged])
        # Atomic, and refuses a non-empty data/ (none can be there: the caller holds the lock).
        os.rename(staged, os.path.join(dataset_dir, "data"))
        sync_directories([dataset_dir])
        _put_metadata(dataset_dir, raw)  # the backup too
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _fsync(path: str) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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


def _commit_batch(dataset_dir: str, first: int, batch: dict, n: int) -> None:
    """Commits the first ``n`` trajectories of a checked batch, episodes ``first ..
    first + n - 1``, as ``.simloader-episodes/<first>-<stop>.hdf5``: written under a
    temporary name, fsync'd, renamed (a torn file is never under the committed name)."""
    import h5py
    folder = os.path.join(dataset_dir, _EPISODES)
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
            for key in ("init", "obs", "control", "diverged"):
                f.create_dataset(key, data=batch[key][:n])
            for key, value in batch["params"].items():
                f.create_dataset(f"params/{key}", data=value[:n])
        _fsync(partial)
        os.replace(partial, final)
        sync_directories([folder])
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise


def _committed(dataset_dir: str) -> list[tuple[int, int, str]]:
    """The committed batch files, ``(first, stop, path)``, sorted (read from the names, no
    file opened)."""
    folder = os.path.join(dataset_dir, _EPISODES)
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    found = [(int(m.group(1)), int(m.group(2)), os.path.join(folder, name))
             for name in names for m in [_BATCH_RE.fullmatch(name)] if m]
    return sorted(found)


def _covered(batches: list[tuple[int, int, str]]) -> int:
    """How many episodes from 0 the batch files hold without a gap."""
    end = 0
    for first, stop, _ in batches:
        if first != end:
            break
        end = stop
    return end


def _prune(dataset_dir: str, keep: int, where: str, fix: str) -> None:
    """Resuming: deletes the batch files from episode ``keep`` on (committed after the last
    recorded count), and checks that those before it hold episodes ``0 .. keep - 1``."""
    kept = []
    for first, stop, path in _committed(dataset_dir):
        if first >= keep:
            os.unlink(path)
        else:
            kept.append((first, stop, path))
    if _covered(kept) != keep or any(stop > keep for _, stop, _ in kept):
        raise ValueError(f"{where}: the incomplete Minari dataset at {dataset_dir} cannot be "
                         f"resumed: its metadata records {keep} episodes written but its "
                         f"{_EPISODES}/ holds committed batch files for episodes 0 to "
                         f"{_covered(kept)} without a gap (written by a simloader that "
                         f"appended to {_MAIN} in place, or edited); {fix}")


def _read_batch(path: str) -> dict:
    import h5py
    with h5py.File(path, "r") as f:
        batch = {key: f[key][()] for key in ("init", "obs", "control", "diverged")}
        batch["params"] = ({key: value[()] for key, value in f["params"].items()}
                           if "params" in f else {})
    return batch


def _finish(dataset_dir: str, total: int) -> None:
    """Assembles Minari's ``main_data.hdf5`` from the committed batch files (in
    ``.simloader-merging/``, fsync'd, renamed over ``data/main_data.hdf5``), sets Minari's
    counts, marks the dataset complete and removes the batch files. Interrupted, it leaves
    the batch files: the next write assembles again."""
    from minari.dataset.minari_storage import MinariStorage

    batches = _committed(dataset_dir)
    if _covered(batches) != total or batches[-1][1] != total:
        raise ValueError(f"path: expected committed batch files for episodes 0 to {total} in "
                         f"{os.path.join(dataset_dir, _EPISODES)}, found them up to "
                         f"{_covered(batches)}")
    data_dir = os.path.join(dataset_dir, "data")
    scratch = os.path.join(dataset_dir, _MERGING)
    shutil.rmtree(scratch, ignore_errors=True)
    os.mkdir(scratch)
    try:
        raw = _read_metadata(dataset_dir)
        _atomic_json(os.path.join(scratch, _METADATA),
                     {**raw, "total_episodes": 0, "total_steps": 0})
        open(os.path.join(scratch, _MAIN), "wb").close()
        storage = MinariStorage.read(scratch)  # plain Minari: its metadata here is scratch
        main, written = os.path.join(scratch, _MAIN), 0
        for first, stop, path in batches:
            # HDF5 can crash the process when the disk fills under it: refuse beforehand
            # what would not fit (Minari's layout is several times the batch files: measured
            # on what is assembled so far, a guess for the first batch)
            per_episode = (os.path.getsize(main) / written if written else
                           16 * os.path.getsize(path) / (stop - first) + 4096)
            _need_space(scratch, int(1.25 * per_episode * (stop - first)) + (1 << 20),
                        f"assembling {_MAIN}" + (f" (about {per_episode * total / 1e6:.1f} "
                                                 f"MB in all)" if written else ""))
            storage.update_episodes(list(_episodes(_read_batch(path), stop - first)))
            written += stop - first
        counts = _read_json(os.path.join(scratch, _METADATA)) or {}
        _fsync(os.path.join(scratch, _MAIN))
        os.replace(os.path.join(scratch, _MAIN), os.path.join(data_dir, _MAIN))
        sync_directories([data_dir])
        raw = _read_metadata(dataset_dir)
        raw.update({k: counts[k] for k in ("total_episodes", "total_steps", "dataset_size")
                    if k in counts})
        state = raw["simloader"]
        state.update(episodes_written=total, complete=True)
        raw["minari_version"] = state["minari_version"]
        _put_metadata(dataset_dir, raw)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    shutil.rmtree(os.path.join(dataset_dir, _EPISODES), ignore_errors=True)
    with contextlib.suppress(OSError):
        os.remove(os.path.join(dataset_dir, _BACKUP))  # complete: nothing left to recover


def _incomplete_version(written: int, total: int) -> str:
    # Shown by Minari as "... the dataset generated by Minari <this>": says what and what to do.
    return (f"{INCOMPLETE_MARK}: {written} of {total} episodes written; a simloader write was "
            f"interrupted. simloader.write(...) with the same dataset resumes it, "
            f"simloader.store.minari.status(path) reports it.")


def _mark(dataset_dir: str, *, episodes_written: int, complete: bool) -> None:
    """Records the progress (atomically), restoring the real ``minari_version`` when complete."""
    raw = _read_metadata(dataset_dir)
    state = raw["simloader"]
    state.update(episodes_written=episodes_written, complete=complete)
    raw["minari_version"] = (state["minari_version"] if complete else
                             _incomplete_version(episodes_written, state["total_episodes"]))
    _put_metadata(dataset_dir, raw)


def _read_json(where: str) -> Optional[dict]:
    try:
        with open(where) as f:
            out = json.load(f)
    except (OSError, ValueError):
        return None
    return out if isinstance(out, dict) else None


def _read_metadata(dataset_dir: str) -> dict:
    """Minari's raw metadata; the backup when a kill truncated it."""
    raw = _read_json(os.path.join(dataset_dir, "data", _METADATA))
    backup = _read_json(os.path.join(dataset_dir, _BACKUP))
    if raw is None and backup is not None:
        return backup
    if raw is None:
        raise ValueError(f"path: expected a Minari dataset with a readable "
                         f"data/{_METADATA} at {dataset_dir}, found none")
    return raw


def _atomic_json(where: str, value: dict) -> None:
    # Minari stores author sets as lists
    atomic_write(where, [json.dumps(value, default=list).encode()], durable=True)


def _put_metadata(dataset_dir: str, raw: dict) -> None:
    _atomic_json(os.path.join(dataset_dir, _BACKUP), raw)
    _atomic_json(os.path.join(dataset_dir, "data", _METADATA), raw)


def _hdf5_episodes(data_dir: str) -> Optional[int]:
    """The number of ``episode_*`` groups in the HDF5 file (None: it cannot be opened now)."""
    import h5py
    try:
        # Without a lock: a shared lock held here would make a writer's open for writing fail.
        with h5py.File(os.path.join(data_dir, _MAIN), "r", locking=False) as f:
            return sum(1 for k in f.keys() if k.startswith("episode_"))
    except (OSError, ValueError, KeyError, RuntimeError):
        return None


def status(path: str | os.PathLike) -> dict:
    """What is at ``path``: a Minari dataset written by simloader, complete or not.

    Reads the metadata without opening the dataset through Minari (which refuses an
    incomplete one), so it works on any state a killed writer left; it takes no lock.

    Args:
      path: the dataset's directory ``<root>/<dataset_id>`` (what ``write`` returns), or its
        ``data/`` directory.

    Returns:
      A dict with ``"path"`` (the dataset directory), ``"exists"``, ``"simloader"`` (it has
      simloader's progress record), ``"complete"`` (True / False; None when unknown: not
      written by simloader with a progress record), ``"episodes_written"`` (episodes recorded
      as durably written), ``"total_episodes"`` (the write's target), ``"episodes_in_file"``
      (complete: the episode groups in ``main_data.hdf5``, None when it cannot be opened;
      incomplete: the episodes of the committed batch files, from their names, counted from
      0 without a gap) and ``"minari_total_episodes"`` (Minari's count in the metadata).
    """
    dataset_dir = os.path.abspath(os.fspath(path))
    if os.path.basename(dataset_dir) == "data" and os.path.exists(
            os.path.join(dataset_dir, _METADATA)):
        dataset_dir = os.path.dirname(dataset_dir)
    out: dict[str, Any] = {"path": dataset_dir, "exists": os.path.exists(dataset_dir),
                           "simloader": False, "complete": None, "episodes_written": None,
                           "total_episodes": None, "episodes_in_file": None,
                           "minari_total_episodes": None}
    if not out["exists"]:
        return out
    try:
        raw = _read_metadata(dataset_dir)
    except ValueError:
        return out
    out["minari_total_episodes"] = raw.get("total_episodes")
    state = raw.get("simloader")
    if isinstance(state, dict) and all(k in state for k in PROGRESS_KEYS):
        out.update(simloader=True, complete=bool(state["complete"]),
                   episodes_written=int(state["episodes_written"]),
                   total_episodes=int(state["total_episodes"]))
    if out["complete"] is False:
        out["episodes_in_file"] = _covered(_committed(dataset_dir))
    else:
        out["episodes_in_file"] = _hdf5_episodes(os.path.join(dataset_dir, "data"))
    return out


@contextlib.contextmanager
def _datasets_root(path: Optional[str | os.PathLike]) -> Iterator[None]:
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


def _check_batch(batch: Any, observation_key: str, index: int,
                 shapes: Optional[tuple[int, int]]) -> dict:
    """The arrays of one batch as numpy, with shapes checked against each other (and against
    the first batch's ``(nobs, nact)`` when ``shapes`` is given); ``params`` as a dict of
    ``(n, ...)`` arrays, keys with ``"/"`` written ``"|"`` (an HDF5 name cannot hold one)."""
    where = f"batches[{index}]"
    if not isinstance(batch, Mapping):
        raise ValueError(f"{where}: expected a dict of arrays, got {type(batch).__name__}")
    missing = [k for k in ("initial_state", observation_key, "control", "diverged")
               if k not in batch]
    if missing:
        raise ValueError(f"{where}: expected keys 'initial_state', {observation_key!r} "
                         f"(observation_key), 'control', 'diverged'; missing {missing}, "
                         f"has {sorted(batch)}")
    init = np.asarray(batch["initial_state"])
    obs = np.asarray(batch[observation_key])
    control = np.asarray(batch["control"])
    diverged = np.asarray(batch["diverged"])
    if obs.ndim != 3:
        raise ValueError(f"{where}[{observation_key!r}]: expected shape (n, nstep, nobs), "
                         f"got {obs.shape}")
    n, nstep, nobs = obs.shape
    if init.shape != (n, nobs):
        raise ValueError(f"{where}['initial_state']: expected shape (n, nobs) = {(n, nobs)} "
                         f"to match {observation_key!r} {obs.shape}, got {init.shape}")
    if control.ndim != 3 or control.shape[:2] != (n, nstep):
        raise ValueError(f"{where}['control']: expected shape (n, nstep, nact) with "
                         f"(n, nstep) = {(n, nstep)} from {observation_key!r}, got {control.shape}")
    if diverged.shape != (n,) or diverged.dtype != np.bool_:
        raise ValueError(f"{where}['diverged']: expected a bool array of shape {(n,)}, "
                         f"got {diverged.dtype} {diverged.shape}")
    if n == 0 or nstep == 0:
        raise ValueError(f"{where}[{observation_key!r}]: expected at least one trajectory of at "
                         f"least one step, got shape {obs.shape}")
    if shapes is not None and (nobs, control.shape[2]) != shapes:
        raise ValueError(f"{where}: expected (nobs, nact) = {shapes} as in batches[0], "
                         f"got {(nobs, control.shape[2])}")
    params = batch.get("params") or {}
    if not isinstance(params, Mapping):
        raise ValueError(f"{where}['params']: expected a dict of (n, ...) arrays, "
                         f"got {type(params).__name__}")
    rows = {}
    for key, value in params.items():
        value = np.asarray(value.numpy() if hasattr(value, "numpy") else value)
        if value.ndim < 1 or value.shape[0] != n:
            raise ValueError(f"{where}['params'][{key!r}]: expected shape (n, ...) with n = "
                             f"{n}, got {value.shape}")
        rows[str(key).replace("/", "|")] = value
    return {"init": init, "obs": obs, "control": control, "diverged": diverged,
            "params": rows}


def _episodes(batch: dict, n: int) -> Iterator[Any]:
    """The first ``n`` trajectories of a checked batch as Minari episode buffers."""
    from minari.data_collector import EpisodeBuffer

    init, obs, control, diverged = batch["init"], batch["obs"], batch["control"], batch["diverged"]
    params = batch.get("params") or {}
    nstep = obs.shape[1]
    for i in range(n):
        observations = np.concatenate([init[i][None].astype(obs.dtype, copy=False), obs[i]])
        terminations = np.zeros(nstep, dtype=bool)
        truncations = np.zeros(nstep, dtype=bool)
        # A trajectory ends either way at its last step: diverged ones because the physics broke
        # (terminal), the others only because the rollout was nstep long (truncated).
        (terminations if diverged[i] else truncations)[-1] = True
        # Minari's infos are per step (nstep + 1 rows, the reset's first): the values the
        # trajectory ran with, on every row.
        infos = ({"params": {key: np.repeat(value[i][None], nstep + 1, axis=0)
                             for key, value in params.items()}} if params else {})
        yield EpisodeBuffer(observations=observations, actions=np.array(control[i]),
                            rewards=np.zeros(nstep), terminations=terminations,
                            truncations=truncations, infos=infos)


def _action_bounds(config: Any) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of each control column: what MuJoCo clamps it to, the widest over the
    models of the pool; unbounded for actuators whose ctrlrange is randomized."""
    import mujoco

    from simloader import controls
    low, high = controls.applied_bounds(config.pool, config.control_spec)
    low, high = np.min(low, axis=0), np.max(high, axis=0)
    if config.randomization is not None and \
            config.control_spec & int(mujoco.mjtState.mjSTATE_CTRL):
        for r in config.randomization.resolved:
            if r.field == "actuator_ctrlrange":  # ctrl comes first in a control row
                actuators = np.unique(np.asarray(r.elements) // 2)
                low[actuators], high[actuators] = -np.inf, np.inf
    return low, high


def write(dataset: Any, path: str | os.PathLike, *, batches: int, metadata: dict,
          progress: bool = True, replace: bool = False) -> str:
    """``simloader.write(dataset, path, batches=, format="minari")``: a Minari dataset.

    Writes ``batches`` batches of ``dataset`` as the Minari dataset named by ``path``'s last
    component (e.g. "cartpole-uniform-v0": Minari ids end in ``-v<N>``), under ``path``'s
    parent as the datasets root. Observations are the recorded ``state`` (needs "state" in
    ``record=`` and ``record_every=1``: Minari holds one action per observation step); each
    episode's ``infos["params"]`` holds its randomized values; the action space is the range
    MuJoCo clamps the controls to (see the module docstring).

    One process writes a dataset at a time (its lock, ``<path>/simloader.lock``): another
    one is refused at once, naming the holder, ``replace=True`` or not. An incomplete dataset
    at ``path`` (a write was killed, or stopped by an exception such as a full disk) of the
    same fingerprint and simulator versions is resumed: the batch files after its last
    recorded count are deleted and the stream continues from there, giving the dataset an
    uninterrupted write gives. Another Minari dataset at ``path`` is refused unless
    ``replace=True``; anything at ``path`` that is not a Minari dataset is refused even then.

    Args:
      dataset: the SimDataset to stream.
      path: ``<datasets root>/<dataset id>``.
      batches: how many batches of the stream (``batches * nbatch`` episodes).
      metadata: the store's provenance (configuration, fingerprint, versions), stored in
        Minari's metadata under "simloader"; its ``fingerprint`` decides whether an
        incomplete dataset at ``path`` can be resumed.
      progress: show a progress bar.
      replace: remove the Minari dataset at ``path`` first and write afresh.

    Returns:
      The dataset's directory.

    Raises:
      ValueError: a dataset that records no ``state`` every step; several ranks; a last path
        component without ``-v<N>``; something not a Minari dataset at ``path``; a complete
        dataset, one of another configuration, or one not written by simloader at ``path``
        (without ``replace=True``); an incomplete one that cannot be resumed.
      StoreLocked: another process is writing the dataset.
      OSError: the disk is full or not writable (the dataset stays incomplete and
        resumable: writing again continues after the batches committed so far).
    """
    from tqdm import tqdm

    from simloader.store.provenance import SIMULATING, differences
    minari = _import_minari()
    c = dataset.config
    if "state" not in [o.key for o in c.observations] or c.record_every != 1:
        raise ValueError(f"format: 'minari' stores the recorded 'state' after every step as "
                         f"observations; the dataset records {[o.key for o in c.observations]} "
                         f"every {c.record_every} step(s): use record=('state', ...) and "
                         f"record_every=1")
    if not isinstance(replace, bool):
        raise ValueError(f"replace: expected True or False, got {replace!r}")
    if (sharding.distributed_rank() or (0, 1))[1] > 1:
        raise ValueError("format: 'minari' is written by one process (an HDF5 file); write "
                         "format='zarr' from several ranks")
    root, dataset_id = os.path.split(os.path.abspath(os.fspath(path)))
    _check_id(dataset_id, "path", f"the last component of {os.fspath(path)!r}")
    metadata = dict(metadata)
    metadata["description"] = f"simloader: {dataset.source}, {batches} x {c.nbatch} trajectories"
    total = _check_args(batches * c.nbatch, metadata, None)
    bounds = _action_bounds(c)
    dataset_dir = _dataset_dir(root, dataset_id)
    where = f"path: {os.fspath(path)!r}"
    fix = "pass replace=True to overwrite it, or write to another path"

    _survey(dataset_dir, where)  # refuses what is not a Minari dataset, before the lock file
    with _locked(dataset_dir, dataset_id):
        try:
            return _write_locked(dataset, os.fspath(path), dataset_id, dataset_dir, batches,
                                 total, metadata, bounds, progress, replace, where, fix,
                                 minari, tqdm, SIMULATING, differences)
        except OSError as e:
            reason = e.strerror or str(e) or type(e).__name__
            raise OSError(e.errno, f"write: {reason} while writing the Minari dataset at "
                                   f"{dataset_dir!r}; it stays incomplete and resumable with "
                                   f"the batches committed so far, and calling write again "
                                   f"(with the space freed) resumes after them",
                          e.filename) from e


def _write_locked(dataset: Any, path: str, dataset_id: str, dataset_dir: str, batches: int,
                  total: int, metadata: dict, bounds: Any, progress: bool, replace: bool,
                  where: str, fix: str, minari: Any, tqdm: Any, SIMULATING: Any,
                  differences: Any) -> str:
    """``write`` once it holds the dataset's lock."""
    c = dataset.config
    kind = _survey(dataset_dir, where)
    if kind == "dataset" and replace:
        _clear(dataset_dir)
        kind = "empty"
    done, create = 0, True
    if kind == "dataset":
        found = status(dataset_dir)
        if not found["simloader"]:
            raise ValueError(f"{where} already holds a Minari dataset without simloader's "
                             f"progress record (written by another tool or an older simloader, "
                             f"so whether it is complete cannot be told); {fix}")
        if found["complete"]:
            shutil.rmtree(os.path.join(dataset_dir, _EPISODES), ignore_errors=True)
            raise ValueError(f"{where} already holds a complete simloader Minari dataset "
                             f"({found['episodes_written']} episodes); {fix}")
        stored = _read_metadata(dataset_dir)["simloader"]
        state = (f"an incomplete simloader Minari dataset ({found['episodes_written']} of "
                 f"{found['total_episodes']} episodes written)")
        differ = differences(stored.get("fingerprint") or {}, metadata.get("fingerprint") or {})
        if differ:
            raise ValueError(f"{where} holds {state} of another configuration "
                             f"({'; '.join(differ)}); it cannot be resumed by this dataset: "
                             f"{fix}")
        old, new = stored.get("versions") or {}, metadata.get("versions") or {}
        stale = [f"{k} {old.get(k)} (now {new.get(k)})" for k in SIMULATING
                 if old.get(k) != new.get(k)]
        if stored["minari_version"] != minari.__version__:
            stale.append(f"minari {stored['minari_version']} (now {minari.__version__})")
        if stale:
            raise ValueError(f"{where} holds {state} written by other versions "
                             f"({', '.join(stale)}); resuming would not continue the same "
                             f"dataset: {fix}")
        done, create = found["episodes_written"], False
        if done % c.nbatch or done > total:
            raise ValueError(f"{where} holds {state}: expected a whole number of batches of "
                             f"{c.nbatch} up to {total} (batches={batches}), got {done} "
                             f"episodes; {fix}")
        _prune(dataset_dir, done, where.split(":")[0], fix)
        _retarget(dataset_dir, metadata, total)
        if done == total:
            _finish(dataset_dir, total)
            return dataset_dir

    bar = tqdm(total=total, initial=done, unit="episode", desc=f"write {path}",
               disable=not progress, leave=False)

    def numpy_batches() -> Iterator[dict[str, Any]]:
        # the stream's batches from the first one not yet written, as format="zarr" stores them
        for _, batch, _ in dataset.stream(dataset.make_backend(), range(done // c.nbatch,
                                                                         batches)):
            out: dict[str, Any] = {k: v.detach().cpu().numpy() for k, v in batch.items()
                                   if k in ("initial_state", "state", "control", "diverged")}
            if "params" in batch:
                out["params"] = {k: v.detach().cpu().numpy()
                                 for k, v in batch["params"].items()}
            yield out

    try:
        return _write(numpy_batches(), dataset_id, dataset_dir, total_episodes=total,
                      observation_key="state", metadata=metadata,
                      progress=lambda n: bar.update(n - bar.n), done=done,
                      first_index=done // c.nbatch, create=create, keep_partial=True,
                      action_bounds=bounds)
    finally:
        bar.close()


def _retarget(dataset_dir: str, metadata: dict, total: int) -> None:
    """Gives a resumed dataset this write's metadata and target (its fingerprint is the
    stored one), as an uninterrupted write of it would have."""
    raw = _read_metadata(dataset_dir)
    state = raw["simloader"]
    raw["simloader"] = {**metadata, **{k: state[k] for k in PROGRESS_KEYS},
                        "total_episodes": total}
    raw["description"] = metadata["description"]
    raw["minari_version"] = _incomplete_version(state["episodes_written"], total)
    _put_metadata(dataset_dir, raw)
