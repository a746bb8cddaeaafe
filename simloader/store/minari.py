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
    opens it without the variable. An existing dataset of that id is never overwritten.

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
    Other keys of a batch (sensordata, ...) are not stored: Minari's per-step ``infos`` need
    ``nstep + 1`` rows (one for the reset) and simloader has none for the initial state.
    observation_space / action_space: ``gymnasium.spaces.Box(-inf, inf, (nobs,) / (nact,), dtype)``
    of the first batch; no gymnasium environment is recorded (``env_spec`` is None).

Metadata
    ``metadata`` (JSON-able dict: config description, fingerprint, versions, ...) is stored whole
    under the key ``"simloader"`` of the dataset's ``data/metadata.json``:
    ``minari.load_dataset(id).storage.metadata["simloader"]``. Minari's own ``description`` is
    ``metadata["description"]`` when that is a string, else a one-line summary.
    ``algorithm_name`` is ``"simloader"``.

Memory
    Minari's ``create_dataset_from_buffers`` takes a list of all episodes, so the dataset is
    created empty with it and each batch is then appended through the public
    ``MinariDataset.update_dataset_from_buffer`` (which appends to the HDF5 file): only the
    batch being written is held. Minari's "hdf5" data format needs the package ``h5py``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import threading
import warnings
from typing import Any, Callable, Iterable, Iterator, Mapping, Optional

import numpy as np

from simloader import sharding

__all__ = ["write_minari"]

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


def write_minari(batches: Iterable[Mapping[str, Any]], path: Optional[str | os.PathLike], *,
                 dataset_id: str, total_episodes: int, observation_key: str = "state",
                 metadata: Optional[dict] = None,
                 progress: Optional[Callable[[int], Any]] = None) -> str:
    """Write ``total_episodes`` simulated trajectories from ``batches`` as the Minari dataset
    ``dataset_id`` under the datasets root ``path``; returns the dataset's directory.

    Batches are consumed until ``total_episodes`` trajectories are written (the last batch is cut
    if it holds more, and no further batch is drawn, so an endless SimDataset works). Fewer
    trajectories than that, a malformed batch or a non-JSON-able ``metadata`` raise ValueError, and
    a partly written dataset is removed. ``progress(n_episodes_done)`` is called after each batch.
    """
    try:
        import minari
        from gymnasium.spaces import Box
    except ImportError as e:
        raise ImportError("write_minari needs minari and gymnasium: "
                          "pip install 'minari>=0.5' h5py") from e

    if not isinstance(dataset_id, str) or not dataset_id:
        raise ValueError(f"dataset_id: expected a non-empty str such as 'simloader/cartpole-v0', "
                         f"got {dataset_id!r}")
    if isinstance(total_episodes, bool) or not isinstance(total_episodes, (int, np.integer)) \
            or total_episodes < 1:
        raise ValueError(f"total_episodes: expected an int >= 1, got {total_episodes!r}")
    total_episodes = int(total_episodes)
    if metadata is not None:
        if not isinstance(metadata, dict):
            raise ValueError(f"metadata: expected a JSON-able dict or None, "
                             f"got {type(metadata).__name__}")
        try:
            json.dumps(metadata)
        except (TypeError, ValueError) as e:
            raise ValueError(f"metadata: expected a JSON-able dict, got one that json cannot "
                             f"write ({e})") from None
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected a callable(n_episodes_done) or None, "
                         f"got {type(progress).__name__}")

    with _datasets_root(path):
        from minari.storage import get_dataset_path
        dataset_dir = os.fspath(get_dataset_path(dataset_id))
    # Checked before any simulation is drawn: Minari would only refuse when creating it.
    if os.path.exists(dataset_dir):
        raise ValueError(f"dataset_id: expected an id not yet used under the datasets root, "
                         f"but {dataset_id!r} already exists at {dataset_dir}")

    it = iter(batches)
    first = next(it, None)
    if first is None:
        raise ValueError(f"batches: expected at least one batch for {total_episodes} episodes, "
                         f"got an empty iterable")
    first = _check_batch(first, observation_key, 0, None)
    nobs, nact = first["obs"].shape[2], first["control"].shape[2]
    observation_space = Box(-np.inf, np.inf, (nobs,), first["obs"].dtype)
    action_space = Box(-np.inf, np.inf, (nact,), first["control"].dtype)
    shapes = (nobs, nact)

    description = (metadata or {}).get("description")
    if not isinstance(description, str):
        description = (f"simloader: {total_episodes} simulated trajectories; observations "
                       f"'{observation_key}' ({nobs}), actions 'control' ({nact}); no reward")

    try:
        with _datasets_root(path), warnings.catch_warnings():
            for message in _NOISE:
                warnings.filterwarnings("ignore", message=message, category=UserWarning)
            # Created empty: the list argument would otherwise hold every episode at once.
            dataset = minari.create_dataset_from_buffers(
                dataset_id, [], env=None, observation_space=observation_space,
                action_space=action_space, algorithm_name="simloader", description=description,
                data_format="hdf5")
    except ImportError as e:
        _remove(dataset_dir)
        raise ImportError("Minari's 'hdf5' data format needs h5py: pip install h5py") from e

    done = 0
    try:
        if metadata is not None:
            dataset.storage.update_metadata({"simloader": metadata})
        batch: Optional[dict] = first
        index = 0
        while True:
            assert batch is not None
            n = min(batch["obs"].shape[0], total_episodes - done)
            dataset.update_dataset_from_buffer(list(_episodes(batch, n)))
            done += n
            batch = None  # let this batch go before the next one is simulated
            if progress is not None:
                progress(done)
            if done >= total_episodes:
                break
            nxt = next(it, None)
            index += 1
            if nxt is None:
                raise ValueError(f"batches: expected {total_episodes} episodes (total_episodes), "
                                 f"but the iterable ended after {done} in {index} batches")
            batch = _check_batch(nxt, observation_key, index, shapes)
    except BaseException:
        # A half-written dataset would load as if complete; remove what this call created.
        _remove(dataset_dir)
        raise
    return dataset_dir


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


def _remove(dataset_dir: str) -> None:
    with contextlib.suppress(OSError):
        shutil.rmtree(dataset_dir)


def _check_batch(batch: Any, observation_key: str, index: int,
                 shapes: Optional[tuple[int, int]]) -> dict:
    """The arrays of one batch as numpy, with shapes checked against each other (and against
    the first batch's ``(nobs, nact)`` when ``shapes`` is given)."""
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
    return {"init": init, "obs": obs, "control": control, "diverged": diverged}


def _episodes(batch: dict, n: int) -> Iterator[Any]:
    """The first ``n`` trajectories of a checked batch as Minari episode buffers."""
    from minari.data_collector import EpisodeBuffer

    init, obs, control, diverged = batch["init"], batch["obs"], batch["control"], batch["diverged"]
    nstep = obs.shape[1]
    for i in range(n):
        observations = np.concatenate([init[i][None].astype(obs.dtype, copy=False), obs[i]])
        terminations = np.zeros(nstep, dtype=bool)
        truncations = np.zeros(nstep, dtype=bool)
        # A trajectory ends either way at its last step: diverged ones because the physics broke
        # (terminal), the others only because the rollout was nstep long (truncated).
        (terminations if diverged[i] else truncations)[-1] = True
        yield EpisodeBuffer(observations=observations, actions=np.array(control[i]),
                            rewards=np.zeros(nstep), terminations=terminations,
                            truncations=truncations)


def write(dataset: Any, path: str, *, batches: int, metadata: dict,
          progress: bool = True) -> str:
    """`simloader.write(dataset, path, batches=, format="minari")`: `batches` batches of
    `dataset` as the Minari dataset named by `path`'s last component (e.g.
    "cartpole-uniform-v0"), under `path`'s parent as the datasets root. Observations are the
    recorded `state` (needs "state" in `record=` and `record_every=1`: Minari holds one
    action per observation step); `metadata` (the store's provenance: configuration,
    fingerprint, versions) goes in Minari's metadata under "simloader". Returns the dataset's
    directory."""
    from tqdm import tqdm
    c = dataset.config
    if "state" not in [o.key for o in c.observations] or c.record_every != 1:
        raise ValueError(f"format: 'minari' stores the recorded 'state' after every step as "
                         f"observations; the dataset records {[o.key for o in c.observations]} "
                         f"every {c.record_every} step(s): use record=('state', ...) and "
                         f"record_every=1")
    root, dataset_id = os.path.split(os.path.abspath(path))
    metadata = dict(metadata)
    metadata["description"] = f"simloader: {dataset.source}, {batches} x {c.nbatch} trajectories"
    if (sharding.distributed_rank() or (0, 1))[1] > 1:
        raise ValueError("format: 'minari' is written by one process (an HDF5 file); write "
                         "format='zarr' from several ranks")
    bar = tqdm(total=batches * c.nbatch, unit="episode", desc=f"write {path}",
               disable=not progress, leave=False)

    def numpy_batches() -> Iterator[dict[str, np.ndarray]]:
        # the stream's first `batches` batches, as format="zarr" stores them with one writer
        for _, batch, _ in dataset.stream(dataset.make_backend(), range(batches)):
            yield {k: v.detach().cpu().numpy() for k, v in batch.items()
                   if k in ("initial_state", "state", "control", "diverged")}

    try:
        return write_minari(numpy_batches(), root, dataset_id=dataset_id,
                            total_episodes=batches * c.nbatch, metadata=metadata,
                            progress=lambda done: bar.update(done - bar.n))
    finally:
        bar.close()
