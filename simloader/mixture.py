"""`Mixture`: one stream of batches drawn from several `SimDataset`s, in a seeded order.

Which member delivers the mixture's `p`-th batch is a pure function of `(seed, p)` (`_Schedule`):
nothing about the schedule has to be saved but the position, and it is the same under any
number of DataLoader workers and on every rank. Worker `w` of `W` takes the positions
`w, w + W, ...` (`sharding.Shard.indices`, as `SimDataset` takes its batch indices), so the
DataLoader's round-robin puts them back in order. Each member is iterated through its own
iterator, started in the same worker, so that member's own sharding gives every worker (and
rank) a disjoint part of its stream and its prefetch thread keeps simulating ahead.

A checkpoint (`state_dict()`) is the next position plus each member's own `state_dict()`:
together they resume the mixture exactly, in each worker.

With `pad=True` a batch holds the rows of `len(datasets)` consecutive draws of the same
schedule (so shares still follow the weights), padded at the end of every trailing axis to the
widest member, with `"task"` per row and `"mask/KEY"` marking the real columns.

The mixture knows no engine: everything it needs comes from the members' configurations and
the batches they deliver.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Optional

import numpy as np
import torch

from simloader import resume, sharding, streams
from simloader.identity import short
from simloader.batch import Batch, flat
from simloader.dataset import SimDataset
from simloader.layout import PARAMS

# a mixture's checkpoint, told apart from a SimDataset's by "kind"
KIND = "simloader.Mixture"
VERSION = 1
# keeps the schedule's random stream apart from any member's (seeds.py spawns (rank, index,
# purpose) keys from the members' seeds; this key has another length, so never coincides)
_SCHEDULE_KEY = 0x6D6978
# schedule draws made at once (one generator per block keeps `member(p)` O(1) amortized)
_BLOCK = 1024


class _Schedule:
    """Which member delivers draw `p`: member `i` with probability `weights[i]`, the same for
    a seed in every process, independently of what was drawn before (draw `p` needs only
    block `p // _BLOCK` of uniforms)."""

    def __init__(self, seed: int, weights: np.ndarray):
        self._seed = seed
        self._cdf = np.cumsum(weights) / weights.sum()
        self._cdf[-1] = 1.0  # no uniform in [0, 1) can fall past the last member by rounding
        self._block: Optional[int] = None
        self._members: np.ndarray = np.zeros(0, np.int64)

    def member(self, p: int) -> int:
        block = p // _BLOCK
        if block != self._block:
            rng = np.random.default_rng(np.random.SeedSequence(
                self._seed, spawn_key=(_SCHEDULE_KEY, block)))
            # side="right": a member of weight 0 (an empty interval) is never drawn
            self._members = np.asarray(np.searchsorted(self._cdf, rng.random(_BLOCK),
                                                       side="right"))
            self._block = block
        return int(self._members[p % _BLOCK])


class Mixture(torch.utils.data.IterableDataset):
    """Batches of several `SimDataset` members in one stream, each member's share following
    `weights`.

    Every item is one member's batch, exactly as that member would deliver it alone
    (bit-identical on the CPU engine), plus `"task"`: a scalar int64 tensor, the member's
    index (in the dict's order). Members keep their own models, engines, sizes, `record=`,
    controls, randomization, policies and `terminate=` rules. Which member comes next is drawn
    from `seed` and the batch's position alone, so the same seed repeats the stream, and the
    order of tasks does not depend on the number of DataLoader workers or the rank (ranks
    simulate the same member at the same step, so DDP does not wait for a rank on a slower
    member; their batches differ, each rank drawing its own part of every member's stream).

    Use it as a `SimDataset`: `DataLoader(mixture, batch_size=None, num_workers=N)` (each
    worker takes a disjoint part of every member's stream), `state_dict()` /
    `load_state_dict()` (or `simloader.loaders.StatefulDataLoader`, torchdata's, which
    refuses by name a state saved with another `num_workers`) to resume exactly. The stream
    ends when the member drawn next has ended (a member with `num_batches`); with endless
    members it is endless. A member belongs to the mixture: iterating it elsewhere at the same
    time would take batches out of the mixture's stream.

    With `pad=True`, each batch instead holds the rows of `len(datasets)` consecutive draws
    (the same schedule: batch j holds draws j*K .. j*K+K-1, K members), concatenated along
    the rows and padded at the end of every trailing axis to the widest member (zeros, False
    for bools), with `"task"` `(nrows,)` int64 per row and, for every key whose width differs
    between members (or that only some members have, as randomized `params`), `"mask/KEY"`
    `(nrows, *trailing shape)` bool: True where a column is real (`"mask/params/KEY"` for
    `batch["params"][KEY]`). A padded column keeps its member's meaning (`describe()`). Members
    must then agree on `nstep`, `record_every`, the recorded keys, the delivered device,
    `dtype=` (None only on one engine: each engine chooses its own), and on having
    `terminate=` rules and a `policy` or not; a 0-d key (`"policy/version"`) becomes one
    value per row.

    Args:
      datasets: `{name: SimDataset}` or a sequence of them (named "0", "1", ...).
      weights: one number >= 0 per member (or `{name: weight}` for a dict), not all 0:
        long-run shares of the batches, normalized (None: equal shares). A member of weight
        0 is never simulated.
      seed: the schedule's seed (int >= 0); members draw their batches from their own seeds.
      pad: mix rows of several members in each batch, padded (see above).

    Raises:
      TypeError, ValueError: bad arguments, naming the argument (the member), the expectation
        and what was given.
    """

    def __init__(self, datasets: Any, weights: Any = None, seed: int = 0, *,
                 pad: bool = False):
        super().__init__()
        self.names, self.datasets = _members(datasets)
        self.weights = _weights(weights, self.names, isinstance(datasets, Mapping))
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise TypeError(f"seed: expected an int >= 0, got {type(seed).__name__} {seed!r}")
        if seed < 0:
            raise ValueError(f"seed: expected an int >= 0, got {seed}")
        if not isinstance(pad, bool):
            raise TypeError(f"pad: expected True or False, got {type(pad).__name__} {pad!r}")
        self.seed, self.pad = int(seed), pad
        # draws per delivered batch: one, or one per member when rows are mixed
        self.group = len(self.datasets) if pad else 1
        self._plan = _pad_plan(self.names, self.datasets) if pad else None
        # workers do not see the process group: keep the rank of the constructing process
        self._rank = sharding.distributed_rank()
        self._position = resume.Position()  # progress: (shard, next position)

    # -- what it is ------------------------------------------------------------------------

    def describe(self) -> str:
        """The tasks: each member's index, name, share and its own `describe()` (which columns
        of its state, control and sensors mean what); with `pad=True`, the padded widths and
        which columns each task fills."""
        lines = [f"Mixture of {len(self.names)} tasks (batch[\"task\"]), seed={self.seed}, "
                 + ("each batch the rows of " + str(self.group) + " draws, padded"
                    if self.pad else "each batch one task's batch")]
        for i, (name, ds) in enumerate(zip(self.names, self.datasets)):
            lines.append(f"task {i} {name!r}: share {self.weights[i]:.4g}")
            lines += ["  " + line for line in ds.describe().splitlines()]
        if self._plan is not None:
            lines.append("padded keys (zeros past a task's own columns; mask/KEY is True on "
                         "the real ones), each task's columns keep the meaning above:")
            for key, (shape, shapes, padded) in self._plan.items():
                fills = "; ".join(
                    f"task {i} {'none' if s is None else _columns(s)}"
                    for i, s in enumerate(shapes))
                lines.append(f"  {key} {shape}{' mask/' + key if padded else ''}: {fills}")
        return "\n".join(lines)

    def reseeded(self, seed: int) -> "Mixture":
        """The same mixture with another `seed`, member i's seed `seed + i` (a new mixture:
        its stream starts afresh)."""
        members = [ds.reseeded(int(seed) + i) for i, ds in enumerate(self.datasets)]
        return Mixture(dict(zip(self.names, members)), list(self.weights), seed, pad=self.pad)

    def members(self, draws: int) -> np.ndarray:
        """The member index of each of the first `draws` draws (batches, or with `pad=True`
        groups of `len(datasets)` rows of a batch), as the schedule draws them."""
        schedule = _Schedule(self.seed, self.weights)
        return np.array([schedule.member(p) for p in range(draws)], dtype=np.int64)

    # -- checkpoints -----------------------------------------------------------------------

    def _config(self) -> dict[str, Any]:
        # what must match for a saved mixture to resume (each member checks its own)
        return {"names": list(self.names), "weights": [float(w) for w in self.weights],
                "seed": self.seed, "pad": self.pad}

    def state_dict(self) -> dict[str, Any]:
        """Where this iterator (this DataLoader worker, or this process) is: the next position
        and every member's own `state_dict()`. JSON-serializable; usable by torchdata's
        `StatefulDataLoader`. Loading it into a mixture of the same configuration resumes
        exactly after the last delivered batch."""
        saved = self._position.saved(lambda: {
            "kind": KIND, "version": VERSION, "config": self._config(), "shard": None,
            "position": None, "members": {n: ds.state_dict()
                                          for n, ds in zip(self.names, self.datasets)}})
        if saved is not None:  # nothing delivered since the last load or iter()
            return saved
        shard, position = self._position.progress
        return {"kind": KIND, "version": VERSION, "config": self._config(),
                "shard": [shard.worker, shard.num_workers, shard.rank], "position": position,
                "members": {n: ds.state_dict() for n, ds in zip(self.names, self.datasets)}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resumes the mixture saved by `state_dict()` at the next iteration.

        Raises:
          ValueError: the state is not a mixture's, or belongs to another configuration (of
            the mixture or of a member, named).
        """
        if not isinstance(state, dict) or state.get("kind") != KIND \
                or state.get("version") != VERSION:
            got = (state.get("kind"), state.get("version")) if isinstance(state, dict) else state
            raise ValueError(f"state_dict: expected a {KIND} state of version {VERSION}, got "
                             f"{short(got)}")
        here, there = self._config(), state.get("config") or {}
        diff = [f"{k} is {short(here[k])} here but {short(there.get(k))} in the "
                f"state" for k in here if here[k] != there.get(k)]
        if diff:
            raise ValueError("state_dict: the saved mixture has another configuration: "
                             + "; ".join(diff))
        members = state.get("members") or {}
        for name, ds in zip(self.names, self.datasets):
            try:  # every member checked before anything is kept: a refusal changes nothing
                resume.check(ds.config, members.get(name))
            except ValueError as e:
                raise ValueError(f"state_dict: member {name!r}: {e}") from None
        self._position.load(state)

    # -- the stream ------------------------------------------------------------------------

    def __iter__(self) -> Iterator[Batch]:
        shard = sharding.current_shard(self._rank)
        loaded = self._position.start(shard, "position")
        start = None if loaded is None else loaded["position"]
        # every member's iterator now (cheap: a member's engine and prefetch thread start at
        # its first batch), each from its saved place or afresh, in this worker, so that its
        # own sharding gives this worker its part of the member's stream
        iterators = []
        for name, ds in zip(self.names, self.datasets):
            if loaded is not None:
                ds.load_state_dict(loaded["members"][name])
            iterators.append(iter(ds))
        return self._batches(shard, start, iterators)

    def _batches(self, shard: sharding.Shard, start: Optional[int],
                 iterators: list[Any]) -> Iterator[Batch]:
        schedule = _Schedule(self.seed, self.weights)
        try:
            for position in shard.indices(None, start):
                draws = [schedule.member(position * self.group + j) for j in range(self.group)]
                batches = []
                for i in draws:
                    try:  # iterators stay alive between draws: prefetch and engines stay hot
                        batches.append(next(iterators[i]))
                    except StopIteration:  # the member drawn has ended: so has the mixture
                        return
                out = self._padded(draws, batches) if self.pad else _tagged(draws[0], batches[0])
                # a member's stream ids, made unique across the members
                out[streams.STREAM] = out[streams.STREAM] * len(self.datasets) + out["task"]
                self._position.progress = (shard, position + shard.num_workers)
                yield out
        finally:
            for it in iterators:  # stops the members' prefetch threads, frees their engines
                it.close()

    def _padded(self, draws: list[int], batches: list[Batch]) -> Batch:
        assert self._plan is not None  # made with pad=True
        return _pad(self._plan, [self.names[i] for i in draws], draws, batches)


# -- checking the arguments ----------------------------------------------------------------

def _members(datasets: Any) -> tuple[tuple[str, ...], tuple[SimDataset, ...]]:
    """(names, datasets) of `datasets`, each a SimDataset, each once."""
    if isinstance(datasets, Mapping):
        for key in datasets:
            if not isinstance(key, str):
                raise TypeError(f"datasets: expected names of type str (the keys of a "
                                f"checkpoint), got {type(key).__name__} {key!r}")
        names, members = tuple(datasets), tuple(datasets.values())
    elif isinstance(datasets, Sequence) and not isinstance(datasets, (str, bytes)):
        names, members = tuple(str(i) for i in range(len(datasets))), tuple(datasets)
    else:
        raise TypeError(f"datasets: expected a dict {{name: SimDataset}} or a sequence of "
                        f"SimDatasets, got {type(datasets).__name__}")
    if not members:
        raise ValueError("datasets: expected at least one SimDataset, got an empty "
                         f"{type(datasets).__name__}")
    seen: dict[int, str] = {}
    for name, ds in zip(names, members):
        if isinstance(ds, Mixture):
            raise TypeError(f"datasets[{name!r}]: expected a SimDataset, got a Mixture (a "
                            f"mixture of mixtures is not supported: list its members instead)")
        if not isinstance(ds, SimDataset):
            hint = ""
            if isinstance(ds, torch.utils.data.Dataset) and not isinstance(
                    ds, torch.utils.data.IterableDataset):
                hint = (" (a map-style dataset such as simloader.StoredDataset yields single "
                        "trajectories, not batches: it cannot be mixed)")
            raise TypeError(f"datasets[{name!r}]: expected a simloader.SimDataset, got "
                            f"{type(ds).__name__}{hint}")
        if id(ds) in seen:  # one iterator per member: a shared one would split its batches
            raise ValueError(f"datasets[{name!r}]: the same SimDataset object as "
                             f"datasets[{seen[id(ds)]!r}]; construct one SimDataset per member")
        seen[id(ds)] = name
    return names, members


def _weights(weights: Any, names: tuple[str, ...], named: bool) -> np.ndarray:
    """The shares, normalized: one finite number >= 0 per member, not all 0."""
    n = len(names)
    if weights is None:
        return np.full(n, 1.0 / n)
    if isinstance(weights, Mapping):
        if not named:
            raise TypeError("weights: a dict of weights needs datasets as a dict of the same "
                            "names; give a sequence of numbers for a sequence of datasets")
        if set(weights) != set(names):
            missing = [k for k in names if k not in weights]
            extra = [k for k in weights if k not in names]
            raise ValueError(f"weights: expected one weight per member {list(names)}; "
                             f"missing {missing}, unknown {extra}")
        weights = [weights[k] for k in names]
    if isinstance(weights, (str, bytes)) or not isinstance(
            weights, (Sequence, np.ndarray, torch.Tensor)):
        raise TypeError(f"weights: expected a sequence of {n} numbers (one per member), got "
                        f"{type(weights).__name__}")
    if len(weights) != n:
        raise ValueError(f"weights: expected {n} numbers (one per member: {list(names)}), got "
                         f"{len(weights)}")
    out = []
    for name, w in zip(names, weights):
        if isinstance(w, torch.Tensor) and w.numel() == 1:
            w = w.item()
        if isinstance(w, bool) or not isinstance(w, (int, float, np.integer, np.floating)):
            raise TypeError(f"weights[{name!r}]: expected a number >= 0, got "
                            f"{type(w).__name__} {w!r}")
        if not math.isfinite(w) or w < 0:
            raise ValueError(f"weights[{name!r}]: expected a finite number >= 0, got {w}")
        out.append(float(w))
    total = sum(out)
    if total <= 0:
        raise ValueError(f"weights: expected at least one weight > 0, got {out}")
    if math.isinf(total):
        # finite weights whose sum overflows (1e308 twice) would all normalize to 0: scaled
        # by the largest first, there only, so that every finite sum normalizes (and a
        # checkpoint's shares compare) bit for bit as before
        largest = max(out)
        out = [w / largest for w in out]
        total = sum(out)
    return np.asarray(out) / total


def _member_device(ds: SimDataset) -> Optional[torch.device]:
    """Where a member delivers, where the member says (`device=`); None where its engine
    decides (the mixture knows no engine: a member's batch then says, and `_pad` refuses
    other devices)."""
    c = ds.config
    return torch.device(c.device) if c.device is not None else None


def _dtype(ds: SimDataset) -> str:
    """The float dtype a member delivers as its configuration says it: its `dtype=`, or None
    and the engine that then chooses (the mixture knows no engine's choice)."""
    c = ds.config
    return str(c.dtype) if c.dtype is not None else f"None (backend {c.backend!r} chooses)"


def _pad_plan(names: tuple[str, ...], datasets: tuple[SimDataset, ...]
              ) -> dict[str, tuple[tuple[int, ...], list, bool]]:
    """Checks that the members can share padded batches; returns, per key of their layouts
    ("params/KEY" for batch["params"][KEY]): (padded trailing shape, each member's trailing
    shape or None, whether a mask is needed)."""
    first, c0 = names[0], datasets[0].config

    def refuse(what: str, name: str, mine: Any, theirs: Any) -> None:
        raise ValueError(f"pad=True: datasets[{name!r}] has {what} {theirs}, "
                         f"datasets[{first!r}] {mine}; padded batches need the same {what} "
                         f"in every member (or use pad=False, one member per batch)")

    device0 = _member_device(datasets[0])
    # a float key of every member (the state where recorded): what a dtype refusal names
    floating = "state" if "state" in datasets[0].layout.keys else "initial_state"
    for name, ds in zip(names[1:], datasets[1:]):
        c = ds.config
        if c.nstep != c0.nstep:
            refuse("nstep", name, c0.nstep, c.nstep)
        if c.record_every != c0.record_every:
            refuse("record_every", name, c0.record_every, c.record_every)
        if c.record_kinematics != c0.record_kinematics:
            refuse("record_kinematics", name, c0.record_kinematics, c.record_kinematics)
        device = _member_device(ds)
        if device is not None and device0 is not None and device != device0:
            refuse("device", name, device0, device)
        # the same dtype=, or None on the same engine: anything else may deliver another
        # dtype, seen only at the first batch whose draws hold both members
        if _dtype(ds) != _dtype(datasets[0]):
            raise ValueError(
                f"pad=True: datasets[{name!r}] has dtype {_dtype(ds)}, datasets[{first!r}] "
                f"{_dtype(datasets[0])}; the float keys of padded batches ({floating!r}, ...) "
                f"need one dtype in every member: give every member the same dtype= (or use "
                f"pad=False, one member per batch)")
        if (c.terminate is None) != (c0.terminate is None):
            refuse("terminate= rules (keys terminated/truncated/first)", name,
                   "set" if c0.terminate is not None else "none",
                   "set" if c.terminate is not None else "none")
        if (c.policy is None) != (c0.policy is None):
            refuse("policy (keys policy/...)", name,
                   "set" if c0.policy is not None else "none",
                   "set" if c.policy is not None else "none")
    recorded = [{k for k in ds.layout.keys if not k.startswith(PARAMS)} for ds in datasets]
    for name, keys in zip(names[1:], recorded[1:]):
        if keys != recorded[0]:
            refuse("recorded keys", name, sorted(recorded[0]), sorted(keys))
    plan: dict[str, tuple[tuple[int, ...], list, bool]] = {}
    ordered = list(datasets[0].layout.keys)
    ordered += [k for ds in datasets[1:] for k in ds.layout.keys if k not in ordered]
    for key in dict.fromkeys(ordered):
        shapes = [ds.layout.keys.get(key) for ds in datasets]
        present = [tuple(s) for s in shapes if s is not None]
        if len({len(s) for s in present}) > 1:
            which = {n: s for n, s in zip(names, shapes) if s is not None}
            raise ValueError(f"pad=True: key {key!r} has trailing shapes of different ranks in "
                             f"the members ({which}): they cannot be padded to one another")
        widest = tuple(max(s[d] for s in present) for d in range(len(present[0])))
        padded = any(s is None or tuple(s) != widest for s in shapes)
        plan[key] = (widest, [None if s is None else tuple(s) for s in shapes], padded)
    return plan


def _columns(shape: tuple[int, ...]) -> str:
    return "[" + ", ".join(f":{n}" for n in shape) + "]"


# -- making the batches --------------------------------------------------------------------

def _tagged(index: int, batch: Batch) -> Batch:
    """The member's batch, its tensors untouched, with "task"."""
    out = Batch(batch, layout=batch.layout)
    out["task"] = torch.tensor(index, dtype=torch.int64, device=_device(batch))
    return out


def _device(batch: Mapping) -> torch.device:
    for value in batch.values():
        if isinstance(value, torch.Tensor):
            return value.device
        if isinstance(value, Mapping):
            return _device(value)
    return torch.device("cpu")


def _pad(plan: dict, names: list[str], tasks: list[int], batches: list[Batch]) -> Batch:
    """The batches' rows in one batch, every key padded to its widest member's trailing shape,
    with "task" per row and "mask/KEY" for each padded key."""
    flats = [flat(b) for b in batches]
    devices = {n: _device(b) for n, b in zip(names, batches)}
    if len(set(devices.values())) > 1:
        raise ValueError(f"pad=True: the members deliver on different devices {devices}; give "
                         f"every member the same device=")
    device = next(iter(devices.values()))
    rows = [int(f["diverged"].shape[0]) for f in flats]
    starts = np.concatenate([[0], np.cumsum(rows)]).tolist()
    nrows = starts[-1]
    out = Batch()
    masks: dict[str, torch.Tensor] = {}
    keys = list(dict.fromkeys(k for f in flats for k in f))
    for key in keys:
        values = [f.get(key) for f in flats]
        dtypes = {n: v.dtype for n, v in zip(names, values) if v is not None}
        if len(set(dtypes.values())) > 1:  # an engine that delivered other than it said
            raise ValueError(f"pad=True: key {key!r} came in dtypes {dtypes} from the members: "
                             f"padded batches need one dtype per key; give every member the "
                             f"same dtype=")
        # a 0-d key (policy/version) becomes one value per row
        values = [v.expand(r) if v is not None and v.dim() == 0 else v
                  for v, r in zip(values, rows)]
        if key in plan:
            widest, shapes, padded = plan[key]
            out_value, mask = _pad_key(values, [shapes[t] for t in tasks], widest, padded,
                                       starts, device)
            if mask is not None:
                masks["mask/" + key] = mask
        else:  # not in the layouts (diverged, flags, policy/...): the same shape everywhere
            out_value = _same_key(key, names, values)
        if key.startswith(PARAMS):
            out.setdefault(PARAMS[:-1], {})[key[len(PARAMS):]] = out_value
        else:
            out[key] = out_value
    # params of the plan no member of this batch randomizes: zeros, masked out, so that every
    # batch has the same keys
    for key, (widest, shapes, padded) in plan.items():
        if key.startswith(PARAMS) and key not in keys:
            dtype = _float_dtype(out)
            out.setdefault(PARAMS[:-1], {})[key[len(PARAMS):]] = torch.zeros(
                (nrows, *widest), dtype=dtype, device=device)
            masks["mask/" + key] = torch.zeros((nrows, *widest), dtype=torch.bool,
                                               device=device)
    out["task"] = torch.cat([torch.full((r,), t, dtype=torch.int64, device=device)
                             for r, t in zip(rows, tasks)])
    out.update(masks)
    return out


def _same_key(key: str, names: list[str], values: list[Optional[torch.Tensor]]
              ) -> torch.Tensor:
    """A key no layout describes, concatenated: every member must deliver it, in one shape."""
    lacking = [n for n, v in zip(names, values) if v is None]
    if lacking:
        raise ValueError(f"pad=True: key {key!r} is delivered by some members but not by "
                         f"{lacking}: padded batches need the same keys from every member")
    present = [v for v in values if v is not None]
    if len({tuple(v.shape[1:]) for v in present}) > 1:
        raise ValueError(f"pad=True: key {key!r} has shapes "
                         f"{dict(zip(names, (tuple(v.shape) for v in present)))} in the "
                         f"members: only the keys of their layouts (recorded keys, control, "
                         f"initial_state, params) are padded")
    return torch.cat(present)


def _pad_key(values: list[Optional[torch.Tensor]], shapes: list[Optional[tuple[int, ...]]],
             widest: tuple[int, ...], padded: bool, starts: list[int], device: torch.device
             ) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """A layout key's values (None: a member without it) in one tensor padded to `widest`,
    and the mask of its real columns (None where no member needs padding)."""
    present = [v for v in values if v is not None]
    sample = present[0]  # every member's in one dtype (checked)
    lead = tuple(sample.shape[1:sample.dim() - len(widest)])  # (nframes,), (nstep,) or ()
    if not padded:  # every member has it, as wide as the widest
        return torch.cat(present), None
    value = torch.zeros((starts[-1], *lead, *widest), dtype=sample.dtype, device=device)
    mask = torch.zeros((starts[-1], *widest), dtype=torch.bool, device=device)
    for v, s, a, b in zip(values, shapes, starts[:-1], starts[1:]):
        if v is None or s is None:
            continue  # a member without this key (params it does not randomize)
        cols = tuple(slice(0, n) for n in s)
        value[(slice(a, b), *[slice(None)] * len(lead), *cols)] = v
        mask[(slice(a, b), *cols)] = True
    return value, mask


def _float_dtype(batch: Mapping) -> torch.dtype:
    # the members share one float dtype (checked): the state's
    return batch["initial_state"].dtype
