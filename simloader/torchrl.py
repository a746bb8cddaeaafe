"""simloader in torchrl: batches as `TensorDict`s in torchrl's keys, and a collector.

`to_tensordict(batch)` lays a simloader batch out as torchrl's collectors do, one row per step,
`batch_size=[nbatch, n]` (rows are trajectories, the time axis second): `observation` (row 0 a
trajectory's `initial_state`), `action` (the row applied after it), `("next", ...)`, the flags
shaped `[..., 1]`, `is_init`, `("collector", "traj_ids")` and `("collector", "mask")` (the rows
that are physics steps). docs/torchrl.md has the full mapping, in one table.

Feed a replay buffer the physics rows: `rb.extend(td[td["collector", "mask"]])` (rows stay in
trajectory order), or `rb.extend(td.reshape(-1))` where every row is one (no `terminate=`,
nothing diverged); `SliceSampler(traj_key=("collector", "traj_ids"))` then never samples a
window across two trajectories (docs/torchrl.md).
"""

from __future__ import annotations

import multiprocessing
import sys
from collections.abc import Iterator, Mapping
from typing import Any, Optional, Union

import torch

# torchrl, as it is imported, makes "spawn" the process-wide default start method where none
# was set; a user's DataLoader workers (of every dataset, not only these) would then start
# as spawned processes instead of the platform's default. Imported first from here, it leaves
# the default as it found it (a user who imports torchrl first has torchrl's).
_untouched = "torchrl" not in sys.modules and \
    multiprocessing.get_start_method(allow_none=True) is None
try:
    from tensordict import TensorDict
    from torchrl.collectors import BaseCollector
except ImportError as e:  # pragma: no cover - said with what to install
    raise ImportError("simloader.torchrl needs torchrl and tensordict: pip install "
                      "'simloader[torchrl]'") from e
if _untouched and multiprocessing.get_start_method(allow_none=True) is not None:
    multiprocessing.set_start_method(None, force=True)

from simloader import policy as simloader_policy
from simloader import streams
from simloader.layout import PARAMS
from simloader.loaders import StatefulDataLoader

PER_TRAJECTORY_FLAGS = ("diverged", "overflow")


def to_tensordict(batch: Mapping[str, Any],
                  observation: Union[str, Mapping[str, str], None] = None) -> TensorDict:
    """A simloader batch as a `TensorDict(batch_size=[nbatch, n])` in torchrl's keys, one row
    per step (the module's table), on the batch's device.

    Args:
      batch: a batch of `SimDataset` or `Mixture` (with the stream keys they deliver).
      observation: which batch keys are observations, and their torchrl names: a batch key
        (named `observation`) or a mapping `{batch key: torchrl key}`, e.g.
        `{"state": "observation", "camera/back/rgb": "pixels"}`. Default: `state` as
        `observation`.

    Raises:
      KeyError: an observation key the batch lacks (naming what it has), or a batch without
        the stream keys.
    """
    names = ({"state": "observation"} if observation is None else
             {observation: "observation"} if isinstance(observation, str) else
             dict(observation))
    if not names:
        raise ValueError("observation: expected at least one batch key to observe, got none")
    missing = [k for k in names if k not in batch]
    if missing:
        raise KeyError(f"observation: the batch has no key {missing[0]!r}; it has "
                       f"{sorted(k for k in batch if k != PARAMS[:-1])}")
    control = batch["control"]
    nbatch = control.shape[0]
    nframes = int(batch[next(iter(names))].shape[1])
    every = control.shape[1] // nframes
    # row 0 starts at the initial state where every observed key has one (only the state)
    lead = set(names) == {"state"}
    skip = 0 if lead else 1  # the frame of the first row's ("next", ...)
    n = nframes - skip
    device = control.device

    def per_frame(key: str) -> torch.Tensor:
        return batch[key][:, skip:]

    def before(key: str) -> torch.Tensor:  # the frame before each row's step
        if lead:
            return torch.cat([batch["initial_state"][:, None], batch[key][:, :-1]], 1)
        return batch[key][:, :-1]

    out: dict[str, Any] = {}
    nxt: dict[str, Any] = {}
    for key, name in names.items():
        out[name], nxt[name] = before(key), per_frame(key)
    steps = control.reshape(nbatch, nframes, every, *control.shape[2:])[:, skip:]
    out["action"] = steps[:, :, 0] if every == 1 else steps
    no = torch.zeros((nbatch, nframes), dtype=torch.bool, device=device)
    first = batch.get("first", no)
    terminated, truncated = batch.get("terminated", no), batch.get("truncated", no)
    nxt["terminated"] = terminated[:, skip:, None]
    nxt["truncated"] = truncated[:, skip:, None]
    nxt["done"] = nxt["terminated"] | nxt["truncated"]
    # per frame from the initial state on (column 0): row t's observation is column t + skip
    firsts = torch.cat([batch[streams.INITIAL_FIRST][:, None], first], 1)
    out["is_init"] = firsts[:, skip:-1, None]
    flagged = torch.zeros(nbatch, dtype=torch.bool, device=device)
    for key in PER_TRAJECTORY_FLAGS:
        if key in batch:
            flagged = flagged | batch[key].to(torch.bool)
    mask = ~first[:, skip:] & ~flagged[:, None]
    ids = streams.trajectory_ids(batch, nframes, initial=True)
    own, after = ids[:, skip:-1], ids[:, 1 + skip:]  # the observation's, the next frame's
    # a row that is no physics step gets an id no trajectory has: -1 - the next frame's
    out["collector"] = {"traj_ids": torch.where(mask, own, -1 - after), "mask": mask}
    version = batch.get(simloader_policy.VERSION)
    if version is not None:
        out["policy_version"] = version.reshape(-1, 1).expand(nbatch, n)
    extras = {k[len(simloader_policy.PREFIX):]: v for k, v in batch.items()
              if k.startswith(simloader_policy.PREFIX) and k != simloader_policy.VERSION}
    if extras:
        out["policy"] = {k: v.reshape(nbatch, nframes, every, *v.shape[2:])[:, skip:, 0]
                         for k, v in extras.items()}
    handled = {*names, "control", "first", "terminated", "truncated", *streams.KEYS,
               simloader_policy.VERSION, *(simloader_policy.PREFIX + k for k in extras)}
    for key, value in batch.items():
        if key in handled:
            continue
        if isinstance(value, Mapping):  # params: one value per trajectory
            out[key] = {k: _rows(v, nbatch, n) for k, v in value.items()}
        elif value.dim() >= 2 and value.shape[0] == nbatch and value.shape[1] == nframes \
                and key != "initial_state":
            nxt[key] = value[:, skip:]
        else:
            out[key] = _rows(value, nbatch, n)
    out["next"] = nxt
    return TensorDict(out, batch_size=[nbatch, n], device=device)


def _copy_weights(policy: Any, weights: Mapping[str, torch.Tensor]) -> None:
    """`weights` (a state dict) copied into the acting `policy` in place, as one counted
    update (`simloader.policy.updating`: no batch copies it half done)."""
    if not isinstance(policy, torch.nn.Module):
        raise TypeError(f"update_policy_weights_: the dataset's policy is a "
                        f"{type(policy).__name__}, not a torch.nn.Module whose weights could "
                        f"be copied")
    own = policy.state_dict(keep_vars=True)
    unknown = [k for k in weights if k not in own and k != "version"]
    if unknown:
        raise KeyError(f"update_policy_weights_: the policy has no weight {unknown[0]!r}; it "
                       f"has {sorted(own)}")
    with torch.no_grad(), simloader_policy.updating(policy):
        for key, value in weights.items():
            if key != "version":  # the update counter is the acting module's own
                own[key].copy_(value)


def _rows(value: torch.Tensor, nbatch: int, n: int) -> torch.Tensor:
    """A per-trajectory value (or a 0-d one, per batch) expanded over the rows: a view."""
    if value.dim() == 0:
        return value.expand(nbatch, n)
    return value[:, None].expand(nbatch, n, *value.shape[1:])


class SimCollector(BaseCollector):
    """A torchrl collector over a `SimDataset` or `Mixture`: iterating it yields each batch
    as `to_tensordict` lays it out, `batch_size=[nbatch, n]`, on the dataset's device (GPU
    engines' batches stay there).

    The dataset's own `policy=` acts (or its controls); `update_policy_weights_(weights)`
    copies new weights into it (a module or a state dict) as one counted update
    (`simloader.policy.updating`). A batch is simulated with one version of the weights,
    copied as it starts, and names it (`policy_version`). Batches run ahead of the consumer,
    so a batch delivered after u updates acts with weights of at least update
    `u - staleness` (`staleness`: `prefetch + 1` in one process; with N DataLoader workers
    `N * (prefetch + 1 + prefetch_factor)`). A mixture's members each run their own
    batches ahead: there `staleness` counts a member's own batches (after an update, a
    member's batches act with it from its `staleness + 1`-th delivery on).

    Args:
      dataset: a `SimDataset` or `Mixture`.
      total_frames: steps (rows) to deliver in all (-1: endless, or until the dataset ends).
      observation: the observation keys and their names (`to_tensordict`).
      num_workers, prefetch_factor, multiprocessing_context: the DataLoader's (0: the
        dataset runs in this process, its policy on the training process's live weights).
    """

    def __init__(self, dataset: Any, *, total_frames: int = -1,
                 observation: Union[str, Mapping[str, str], None] = None,
                 num_workers: int = 0, prefetch_factor: Optional[int] = None,
                 multiprocessing_context: Any = None):
        super().__init__()
        if not hasattr(dataset, "reseeded") or not isinstance(
                dataset, torch.utils.data.IterableDataset):
            raise TypeError(f"dataset: expected a simloader SimDataset or Mixture, got "
                            f"{type(dataset).__name__}")
        if isinstance(total_frames, bool) or not isinstance(total_frames, int) \
                or (total_frames < 1 and total_frames != -1):
            raise ValueError(f"total_frames: expected a positive int or -1 (endless), got "
                             f"{total_frames!r}")
        self.observation, self.total_frames = observation, total_frames
        self.num_workers = num_workers
        self._loader_kwargs: dict[str, Any] = {}
        if num_workers:
            self._loader_kwargs = {"num_workers": num_workers,
                                   "prefetch_factor": prefetch_factor,
                                   "multiprocessing_context": multiprocessing_context}
        self._use(dataset)
        prefetch = self._members[0].config.prefetch
        self.staleness = (prefetch + 1 if not num_workers else
                          num_workers * (prefetch + 1 + (prefetch_factor or 2)))
        self._frames = 0
        self._live: Optional[Iterator] = None

    def _use(self, dataset: Any) -> None:
        """Collects from `dataset` (in this process, or through a DataLoader's workers)."""
        self.dataset = dataset
        self._members = getattr(dataset, "datasets", (dataset,))
        # the acting policies (a mixture's members may share one module, or have their own)
        self.policies = list({id(m.config.policy): m.config.policy for m in self._members
                              if m.config.policy is not None}.values())
        first = self._members[0].config
        self.frames_per_batch = self.requested_frames_per_batch = first.nbatch * first.nframes
        self.loader = (StatefulDataLoader(dataset, batch_size=None, **self._loader_kwargs)
                       if self.num_workers else None)

    def __len__(self) -> int:
        """Batches it delivers: by `total_frames`, else the dataset's `num_batches` (per
        rank). TypeError where endless (so that `list(collector)` and `len` work as on a
        sized iterable)."""
        if self.total_frames > 0:
            return -(self.total_frames // -self.frames_per_batch)
        return len(self.dataset)  # TypeError where endless

    def iterator(self) -> Iterator[TensorDict]:
        """Yields the batches as TensorDicts until `total_frames` rows were delivered."""
        self._live = iter(self.loader if self.loader is not None else self.dataset)
        try:
            for batch in self._live:
                td = to_tensordict(batch, self.observation)
                self._frames += td.numel()
                yield td
                if self.total_frames != -1 and self._frames >= self.total_frames:
                    return
        finally:
            self._close_live()

    def update_policy_weights_(self, policy_or_weights: Any = None, *,
                               worker_ids: Any = None, **kwargs: Any) -> None:
        """Brings the acting policy (each of a mixture's members') to new weights: a module
        (its parameters and buffers are copied) or a state dict, in one counted update; None when the training loop updated
        the dataset's policy module itself (nothing to copy: the next batch begun copies
        its weights). Batches already begun keep the weights they began with (`staleness`).

        Raises:
          ValueError: the dataset has no `policy=`.
          KeyError: a weight the policy does not have.
        """
        if not self.policies:
            raise ValueError("update_policy_weights_: the dataset has no policy= (its "
                             "controls act): there are no weights to update")
        if policy_or_weights is None:
            return
        weights = (policy_or_weights.state_dict()
                   if isinstance(policy_or_weights, torch.nn.Module) else policy_or_weights)
        for policy in self.policies:
            _copy_weights(policy, weights)

    def set_seed(self, seed: int, static_seed: bool = False) -> int:
        """Collects from now on from the dataset made again with `seed` (`SimDataset.
        reseeded`; a mixture's member i gets `seed + i`): a new stream, from its start.
        Returns the seed."""
        self._close_live()
        self._use(self.dataset.reseeded(int(seed)))
        return int(seed)

    def state_dict(self) -> dict[str, Any]:
        """The stream's place (the dataset's `state_dict()`, or with workers the loader's:
        every worker's place in its stream) and the rows delivered."""
        saved = self.loader if self.loader is not None else self.dataset
        return {"stream": saved.state_dict(), "frames": self._frames}

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        """Resumes after the last batch of `state_dict()`, at the next iteration."""
        saved = self.loader if self.loader is not None else self.dataset
        saved.load_state_dict(state_dict["stream"])
        self._frames = int(state_dict["frames"])

    def shutdown(self, timeout: Optional[float] = None, close_env: bool = True,
                 raise_on_error: bool = True) -> None:
        """Stops the stream: its producer threads, engines and DataLoader workers."""
        self._close_live()

    def _close_live(self) -> None:
        live, self._live = self._live, None
        if live is not None:
            shutdown = getattr(live, "_shutdown_workers", None)
            if shutdown is not None:
                shutdown()
            close = getattr(live, "close", None)
            if close is not None:
                close()
