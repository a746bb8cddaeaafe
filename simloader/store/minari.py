"""Write simulated trajectories as a Minari dataset (offline-RL format), streamed batch by batch.

    from simloader.store.minari import write_minari
    ds = simloader.SimDataset("cartpole", nbatch=256, nstep=200, num_batches=40,
                              control=simloader.controls.Uniform())
    batches = ({k: v.numpy() for k, v in b.items()} for b in ds)
    write_minari(batches, "datasets", dataset_id="simloader/cartpole/uniform-v0",
                 total_episodes=256 * 40)
    # later, with MINARI_DATASETS_PATH=datasets:
    minari.load_dataset("simloader/cartpole/uniform-v0")

This module holds the writers' entries (``write``, the format's writer, and ``write_minari``)
and ``status``; the rest is in modules of their own:

    minari_episodes.py  a batch's trajectories as Minari episodes, the action space
    minari_folder.py    the dataset's directory: what is there, its lock, what killed
                        writers left, its removal; Minari's datasets root
    minari_metadata.py  Minari's metadata.json and simloader's progress record in it
    minari_hdf5.py      the HDF5 files, never modified in place: creation, batch files,
                        resuming, the assembly of main_data.hdf5

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
import json
import os
import shutil
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional

import numpy as np

from simloader import sharding
from simloader.store.minari_episodes import (EPISODE_FLAGS, action_space, applied_action_bounds,
                                             check_batch)
from simloader.store.minari_folder import (EPISODES, METADATA, clear, dataset_dir_of, locked,
                                           survey)
from simloader.store.minari_hdf5 import (commit_batch, committed, covered, create_empty, finish,
                                         hdf5_episodes, prune)
from simloader.store.minari_metadata import (INCOMPLETE_MARK, PROGRESS_KEYS, mark,
                                             read_metadata, retarget)

__all__ = ["write_minari", "write", "status", "INCOMPLETE_MARK", "PROGRESS_KEYS"]


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
    dataset_dir = dataset_dir_of(path, dataset_id)
    where = f"dataset_id: {dataset_id!r}"

    def refuse_existing() -> None:
        raise ValueError(f"dataset_id: expected an id not yet used under the datasets root, "
                         f"but {dataset_id!r} already exists at {dataset_dir}")

    # Checked before any simulation is drawn: Minari would only refuse when creating it.
    if survey(dataset_dir, where) == "dataset":
        refuse_existing()
    with locked(dataset_dir, dataset_id):
        if survey(dataset_dir, where) == "dataset":
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


def write(dataset: Any, path: str, *, batches: int, num_workers: int, progress: bool,
          replace: bool) -> str:
    """``simloader.write(dataset, path, batches=, format="minari")``: a Minari dataset (the
    writer `simloader.store.formats` names, its arguments checked by `simloader.write`).

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
      num_workers: not used: the dataset is streamed in this process.
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

    from simloader.store.provenance import SIMULATING, differences, provenance
    # stored in Minari's metadata under "simloader": its fingerprint decides whether an
    # incomplete dataset at `path` can be resumed
    metadata = provenance(dataset, batches)
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
    metadata["description"] = f"simloader: {dataset.source}, {batches} x {c.nbatch} trajectories"
    total = _check_args(batches * c.nbatch, metadata, None)
    bounds = applied_action_bounds(c)
    dataset_dir = dataset_dir_of(root, dataset_id)
    where = f"path: {os.fspath(path)!r}"
    fix = "pass replace=True to overwrite it, or write to another path"

    survey(dataset_dir, where)  # refuses what is not a Minari dataset, before the lock file
    with locked(dataset_dir, dataset_id):
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
    kind = survey(dataset_dir, where)
    if kind == "dataset" and replace:
        clear(dataset_dir)
        kind = "empty"
    done, create = 0, True
    if kind == "dataset":
        found = status(dataset_dir)
        if not found["simloader"]:
            raise ValueError(f"{where} already holds a Minari dataset without simloader's "
                             f"progress record (written by another tool or an older simloader, "
                             f"so whether it is complete cannot be told); {fix}")
        if found["complete"]:
            shutil.rmtree(os.path.join(dataset_dir, EPISODES), ignore_errors=True)
            raise ValueError(f"{where} already holds a complete simloader Minari dataset "
                             f"({found['episodes_written']} episodes); {fix}")
        stored = read_metadata(dataset_dir)["simloader"]
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
        prune(dataset_dir, done, where.split(":")[0], fix)
        retarget(dataset_dir, metadata, total)
        if done == total:
            finish(dataset_dir, total)
            return dataset_dir

    bar = tqdm(total=total, initial=done, unit="episode", desc=f"write {path}",
               disable=not progress, leave=False)

    def numpy_batches() -> Iterator[dict[str, Any]]:
        # the stream's batches from the first one not yet written, as format="zarr" stores them
        for _, batch in dataset.batches_at(range(done // c.nbatch, batches)):
            out: dict[str, Any] = {k: v.detach().cpu().numpy() for k, v in batch.items()
                                   if k in ("initial_state", "state", "control", "diverged",
                                            *EPISODE_FLAGS)}
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
    first = check_batch(first, observation_key, first_index, None)
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
            create_empty(minari, dataset_id, dataset_dir, description, total_episodes, metadata,
                         Box(-np.inf, np.inf, (nobs,), first["obs"].dtype),
                         action_space(action_bounds, nact, first["control"].dtype))
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
            commit_batch(dataset_dir, done, batch, n)
            done += n
            batch = None  # let this batch go before the next one is simulated
            # After the commit: the recorded count never exceeds what is committed.
            mark(dataset_dir, episodes_written=done, complete=False)
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
            batch = check_batch(nxt, observation_key, index, shapes)
        finish(dataset_dir, total_episodes)
    except BaseException:
        if create and not keep_partial:
            # A half-written dataset is marked incomplete, but this caller cannot resume it.
            with contextlib.suppress(OSError):
                clear(dataset_dir)
        raise
    return dataset_dir


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
            os.path.join(dataset_dir, METADATA)):
        dataset_dir = os.path.dirname(dataset_dir)
    out: dict[str, Any] = {"path": dataset_dir, "exists": os.path.exists(dataset_dir),
                           "simloader": False, "complete": None, "episodes_written": None,
                           "total_episodes": None, "episodes_in_file": None,
                           "minari_total_episodes": None}
    if not out["exists"]:
        return out
    try:
        raw = read_metadata(dataset_dir)
    except ValueError:
        return out
    out["minari_total_episodes"] = raw.get("total_episodes")
    state = raw.get("simloader")
    if isinstance(state, dict) and all(k in state for k in PROGRESS_KEYS):
        out.update(simloader=True, complete=bool(state["complete"]),
                   episodes_written=int(state["episodes_written"]),
                   total_episodes=int(state["total_episodes"]))
    if out["complete"] is False:
        out["episodes_in_file"] = covered(committed(dataset_dir))
    else:
        out["episodes_in_file"] = hdf5_episodes(os.path.join(dataset_dir, "data"))
    return out
