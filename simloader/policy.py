"""Closed loop: the user's policy, as both backends call it.

`SimDataset(policy=...)` calls the policy once per step, before the step, with the current
observations (a dict of tensors `nbatch x ...`, keys as in `record`, on the dataset's device);
it returns the control rows (`nbatch x ncontrol`, the `control_spec` layout) or a pair
`(control, extras)` whose extras (tensors `nbatch x ...`) are delivered as `"policy/KEY"`,
`nbatch x nstep x ...`. The backends drive the loop (`backends/cpu/`: `mujoco.batch`'s
`step()`; `backends/mjx/closed_loop.py`: one jitted step per call); this module holds what they
share: calling and checking the policy, its extras, its weights' version, and the rule for
DataLoader workers.
"""

from __future__ import annotations

import contextlib
import copy
import threading
import time
import weakref
from collections.abc import Callable, Iterator, Mapping
from typing import Any, Optional

import torch

PREFIX = "policy/"
# batch key: which update of the weights produced the batch (read as the batch starts)
VERSION = "policy/version"


def check(policy: Any) -> None:
    """Raises TypeError unless `policy` is callable."""
    if not callable(policy):
        raise TypeError(f"policy: expected a callable (e.g. a torch.nn.Module) mapping a dict of "
                        f"observation tensors to control rows, got {type(policy).__name__}")


def version(policy: Any) -> int:
    """Which update of the weights the policy is at now.

    The policy's own `version` attribute (an int the training loop bumps after each update, or
    a one-element integer tensor, e.g. a buffer in shared memory that DataLoader workers
    read) if it has one; else, for a `torch.nn.Module`, the sum of torch's version counters of its
    parameters and buffers, which every in-place update (`optimizer.step()`,
    `param.copy_()`, ...) increases, plus a process-local offset that moves it past every
    value it had whenever a parameter or buffer is replaced by another object
    (`module.weight = nn.Parameter(...)`, `load_state_dict(..., assign=True)`), whose new
    tensors' counters start again at 0; else -1 (unknown).
    """
    own = getattr(policy, "version", None)
    if isinstance(own, int) and not isinstance(own, bool):
        return own
    if isinstance(own, torch.Tensor) and own.numel() == 1 and not own.is_floating_point():
        return int(own)  # a shared counter buffer: what DataLoader workers can see
    if isinstance(policy, torch.nn.Module):
        return _module_version(policy)
    return -1


class _Seen:
    """A module's tensors when its version was last read (weak references: an identity check
    that a freed and reused address cannot fool), the offset added to its counters' sum, and
    the last version returned."""

    __slots__ = ("refs", "offset", "last")

    def __init__(self) -> None:
        self.refs: Optional[tuple] = None  # None: never read
        self.offset = 0
        self.last = -1


# per module without a `version` attribute: what `version` saw last (this process only)
_SEEN: "weakref.WeakKeyDictionary[Any, _Seen]" = weakref.WeakKeyDictionary()
_SEEN_LOCK = threading.Lock()


def _module_version(policy: torch.nn.Module) -> int:
    """The sum of the counters of the module's tensors, moved past every earlier value when a
    tensor was replaced by another object since the last call (one identity check per tensor:
    no copies, no synchronisation)."""
    tensors = _tensors(policy)
    total = sum(t._version for t in tensors)
    with _SEEN_LOCK:
        seen = _SEEN.get(policy)
        if seen is None:
            seen = _SEEN[policy] = _Seen()
        same = seen.refs is not None and len(seen.refs) == len(tensors) and all(
            r() is t for r, t in zip(seen.refs, tensors))
        if not same:
            if seen.refs is not None:  # replaced or added: one past the last version returned
                seen.offset = max(seen.offset, seen.last + 1 - total)
            seen.refs = tuple(weakref.ref(t) for t in tensors)
        value = int(total + seen.offset)
        seen.last = max(seen.last, value)
        return value


# modules whose weights a training loop is updating now (`updating`), for those without a
# `version` attribute, whose in-progress mark lives in this process only
_IN_UPDATE: "weakref.WeakKeyDictionary[Any, int]" = weakref.WeakKeyDictionary()


@contextlib.contextmanager
def updating(policy: Any) -> Iterator[None]:
    """Marks an update of the policy's weights as in progress, and counts it when it ends.

    ``with simloader.policy.updating(policy): optimizer.step()``. No batch copies weights
    while the update runs, and the batches after it name the version it made. Without it, a
    multi-tensor update may be copied half done (torch's counters move per tensor), and a
    shared `version` bumped after the update leaves a moment where a batch copies the new
    weights under the old version. The writer's side of a sequence lock: a `version` attribute
    (an int, or the shared integer buffer DataLoader workers read) holds -(v + 2) during the
    update (below -1, the "unknown" version) and v + 1 after it; a module without one is
    marked in this process only.
    """
    counter = getattr(policy, "version", None)
    if isinstance(counter, torch.Tensor) and counter.numel() == 1 \
            and not counter.is_floating_point():
        before = int(counter)
        with torch.no_grad():
            counter.fill_(-(before + 2))
            try:
                yield
            finally:
                counter.fill_(before + 1)
    elif isinstance(counter, int) and not isinstance(counter, bool):
        policy.version = -(counter + 2)
        try:
            yield
        finally:
            policy.version = counter + 1
    elif counter is None:
        _IN_UPDATE[policy] = _IN_UPDATE.get(policy, 0) + 1
        try:
            yield
        finally:
            _IN_UPDATE[policy] -= 1
    else:
        raise TypeError(f"policy.version: expected an int or a one-element integer tensor "
                        f"(the update counter), got {type(counter).__name__}")


UPDATE_WAIT_S = 60.0  # an update still in progress after this long is a crashed trainer


def _in_update(policy: Any) -> bool:
    return version(policy) < -1 or _IN_UPDATE.get(policy, 0) > 0


def _tensors(policy: torch.nn.Module) -> list[torch.Tensor]:
    return [*policy.parameters(), *policy.buffers()]


def check_worker(policy: Any) -> None:
    """In a DataLoader worker: refuses a policy whose weights would be a frozen copy.

    A worker gets a copy of the policy when it starts; updates made by the training process
    reach it only through shared memory (`module.share_memory()` before the DataLoader starts
    its workers, CPU tensors). A module with every parameter and buffer shared is accepted if
    it carries a shared version counter (a `version` buffer), so that its batches name the
    update that made them.

    Raises:
      RuntimeError: a policy that is not a module whose tensors are all in shared memory.
    """
    if torch.utils.data.get_worker_info() is None:
        return
    if isinstance(policy, torch.nn.Module):
        tensors = _tensors(policy)
        if all(t.is_shared() and t.device.type == "cpu" for t in tensors):
            counter = getattr(policy, "version", None)
            if isinstance(counter, torch.Tensor) and counter.is_shared():
                return
            # torch's own version counters live in each process: a worker would name every
            # batch with the version it started with
            raise RuntimeError(
                "policy: a DataLoader worker sees the shared weights but not which update "
                "they are; give the policy a shared version counter: "
                "policy.register_buffer('version', torch.zeros((), dtype=torch.int64)) "
                "before policy.share_memory(), then update the weights inside "
                "`with simloader.policy.updating(policy): optimizer.step()`, which counts "
                "the update; or use num_workers=0")
    raise RuntimeError(
        "policy: a DataLoader worker holds a copy of the policy made when it started, so the "
        "training loop's updates would never reach it; use num_workers=0 (the policy runs in "
        "a thread of the training process, on its live weights), or a CPU torch.nn.Module "
        "whose tensors are in shared memory (call policy.share_memory() before iterating)")


class Snapshot:
    """The weights each batch runs with: one version of them for the whole batch.

    A training loop updates the live module while the producer thread simulates, so a policy
    called step by step would mix the weights of several updates in one batch. At the start
    of every batch the module's parameters and buffers are copied into a private copy of the
    module (made once), which the batch calls; the copy is queued on each GPU's default stream,
    where a training loop queues its updates, so it reads whole updates only. It is taken
    again if the version moved meanwhile or an update marked by `updating` ran, and waits
    while one runs. Cost: one copy of the weights per batch. A callable that is not a module
    is called live (its version is its own `version`, or -1).
    """

    def __init__(self, policy: Any, device: Optional[torch.device] = None):
        self.policy = policy
        # where the batch simulates: a module on another device (`sim_device=`) runs as a
        # copy there, its weights copied across at every batch
        self.device = device
        self.frozen: Optional[torch.nn.Module] = None

    def take(self) -> tuple[Callable, int]:
        """(what to call this batch, the version of its weights)."""
        live = self.policy
        if not isinstance(live, torch.nn.Module):
            return live, version(live)
        if self.frozen is None:
            try:
                self.frozen = copy.deepcopy(live)
            except Exception as e:  # noqa: BLE001 - said with what to do
                raise TypeError(f"policy: simloader runs each batch on a copy of the policy's "
                                f"weights (one version per batch) and could not copy this "
                                f"module ({type(e).__name__}: {e}); make it deep-copyable") \
                    from None
            if self.device is not None:
                self.frozen.to(self.device)  # in place; nothing moves where it already is
        mine = _tensors(self.frozen)
        # the reader's side of the sequence lock (`updating`): copy while no update runs, and
        # keep the copy only if none ran meanwhile (a tensor replaced by another object moves
        # the version too, so the tensors are listed again after reading it)
        start = time.monotonic()
        while True:
            before = version(live)
            if not _in_update(live):
                _copy_in_order(mine, _tensors(live))
                if version(live) == before and not _in_update(live):
                    return self.frozen, before
            if time.monotonic() - start > UPDATE_WAIT_S:
                raise RuntimeError(
                    f"policy: no copy of its weights without an update running in "
                    f"{UPDATE_WAIT_S:.0f} s (the version stayed below -1, was marked by "
                    f"simloader.policy.updating, or moved during every copy); did the training "
                    f"loop stop inside an update?")
            time.sleep(1e-5)


def _copy_in_order(mine: list, theirs: list) -> None:
    """`mine[i].copy_(theirs[i])`, GPU tensors on their device's default stream (after the
    updates a training loop queued there), the caller's stream then waiting for the copies."""
    with torch.no_grad():
        for device in {t.device for t in theirs if t.is_cuda}:
            stream = torch.cuda.default_stream(device)
            with torch.cuda.stream(stream):
                for a, b in zip(mine, theirs):
                    if b.device == device:
                        a.copy_(b)
            torch.cuda.current_stream(device).wait_stream(stream)
        for a, b in zip(mine, theirs):
            if not b.is_cuda:
                a.copy_(b)


class Observations(dict):
    """The dict of observation tensors the policy receives: its keys are the batch keys that
    `record=` names, and a missing key says so (a bare `KeyError: 'qpos'` does not)."""

    def __missing__(self, key: Any) -> Any:
        raise KeyError(f"policy: the observations have no key {key!r}; their keys follow "
                       f"record= (the batch keys), here {list(self)}; add {key!r} to record= "
                       f"to observe it")


def _float_dtypes(tensors: Any) -> set:
    return {t.dtype for t in tensors if isinstance(t, torch.Tensor) and t.is_floating_point()}


def _dtype_advice(policy: Any, obs: Mapping[str, Any]) -> Optional[str]:
    """Why a policy fails on these observations' dtype, with the fix, or None: a
    `torch.nn.Module` whose floating parameters have another dtype than the observations."""
    if not isinstance(policy, torch.nn.Module):
        return None
    params, seen = _float_dtypes(_tensors(policy)), _float_dtypes(obs.values())
    if not params or not seen or params & seen:
        return None
    mine, theirs = sorted(map(str, params)), sorted(map(str, seen))
    fix = ("SimDataset(..., dtype=torch.float32) or policy.double()"
           if torch.float64 in seen else "SimDataset(..., dtype=torch.float64) or policy.float()")
    return (f"policy, dtype: the policy's parameters are {', '.join(mine)} but its observations "
            f"are {', '.join(theirs)} (the dataset's dtype; dtype=None delivers float64 on "
            f"backend='cpu', float32 on backend='mjx'); pass {fix}")


def _dict_advice(policy: Any, obs: Mapping[str, Any], error: Exception) -> Optional[str]:
    """Why a policy fails on being given the observations as a dict, with the wrapper to
    write, or None: a network that expects a tensor (`torch.nn.Sequential(torch.nn.Linear(n,
    m))`) raises a TypeError or AttributeError that names the dict's type."""
    said = str(error)
    if not isinstance(error, (TypeError, AttributeError)) or not any(
            w in said for w in (type(obs).__name__, "'dict'", " dict")):
        return None
    shapes = ", ".join(f"{k!r}: {tuple(v.shape)}" for k, v in obs.items()
                       if isinstance(v, torch.Tensor))
    first = next(iter(obs), "state")
    dtype = _dtype_advice(policy, obs)
    return (f"policy: it is called with a dict of observation tensors, not a tensor: keys "
            f"{list(obs)} (as record= names them; shapes {{{shapes}}}), and calling it "
            f"raised {type(error).__name__}: {error}; "
            f"wrap the network in a module whose forward picks its input from the dict:\n\n"
            f"    class Policy(torch.nn.Module):\n"
            f"        def __init__(self, net):\n"
            f"            super().__init__()\n"
            f"            self.net = net\n\n"
            f"        def forward(self, obs):\n"
            f"            return self.net(obs[{first!r}])\n\n"
            f"    SimDataset(..., policy=Policy(net))"
            + (f"\n\nand match the dtypes: {dtype}" if dtype else ""))


class Caller:
    """Calls the policy for one batch and checks what it returns.

    Args:
      policy: the user's callable.
      nbatch, ncontrol: the expected control rows.
      nstep: steps per batch (the extras' second axis).
      device: where the extras are kept (the dataset's device, or the CPU).
    """

    def __init__(self, policy: Callable, nbatch: int, ncontrol: int, nstep: int,
                 device: Optional[torch.device]):
        self.policy, self.nbatch, self.ncontrol, self.nstep = policy, nbatch, ncontrol, nstep
        if device is not None and device.type == "cuda" and device.index is None:
            # device="cuda" is the current CUDA device, where the policy's rows then are
            # ("cuda:0" is no torch.device("cuda") to `!=`)
            device = torch.device("cuda", torch.cuda.current_device())
        self.device = device
        self.extras: dict[str, torch.Tensor] = {}

    def __call__(self, obs: dict[str, torch.Tensor], t: int) -> torch.Tensor:
        """The control rows of step `t` (a tensor `nbatch x ncontrol`); the extras are kept in
        `self.extras` (`"policy/KEY"`: `nbatch x nstep x ...`)."""
        if not isinstance(obs, Observations):
            obs = Observations(obs)
        try:
            with torch.no_grad():
                out = self.policy(obs)
        except (RuntimeError, TypeError, AttributeError) as e:
            advice = _dict_advice(self.policy, obs, e)
            if advice is not None:
                raise TypeError(advice) from e
            if isinstance(e, AttributeError):
                raise
            # not refused up front: a policy may convert its inputs itself (obs.float())
            advice = _dtype_advice(self.policy, obs)
            said = str(e).lower()
            if advice is None or not any(w in said for w in ("dtype", "scalar type", "double",
                                                               "float")):
                raise
            raise TypeError(f"{advice} (calling it raised {type(e).__name__}: {e})") from e
        control, extras = out if isinstance(out, tuple) and len(out) == 2 else (out, None)
        # every step's rows are checked, not only the first's: a (1, ncontrol) or (ncontrol,)
        # tensor at a later step would broadcast to every trajectory (host-side metadata only:
        # no synchronisation with the device)
        self._check(control, extras, t)
        if t == 0:
            self.extras = {PREFIX + k: torch.empty((self.nbatch, self.nstep, *v.shape[1:]),
                                                   dtype=v.dtype, device=v.device)
                           for k, v in (extras or {}).items()}
        for k, v in (extras or {}).items():
            self.extras[PREFIX + k][:, t] = v
        return control

    def _check(self, control: Any, extras: Any, t: int) -> None:
        at = f" at step {t}" if t else ""
        expected = (self.nbatch, self.ncontrol)
        if not isinstance(control, torch.Tensor):
            raise TypeError(f"policy: expected it to return control rows as a torch.Tensor "
                            f"{expected} (or a pair (control, extras)){at}, got "
                            f"{type(control).__name__}")
        if tuple(control.shape) != expected:
            raise ValueError(f"policy: control rows must have shape (nbatch, ncontrol) = "
                             f"{expected} (the control_spec layout){at}, got "
                             f"{tuple(control.shape)}")
        if not control.is_floating_point():
            raise TypeError(f"policy: control rows must be floating point{at}, got "
                            f"{control.dtype}")
        if self.device is not None and control.device != self.device:
            raise ValueError(f"policy: control rows must be on the dataset's device "
                             f"{self.device}{at}, got {control.device}")
        if t and (extras is None) != (not self.extras):
            raise ValueError(f"policy: it returned {'no ' if extras is None else ''}extras"
                             f"{at}, but {'' if self.extras else 'no '}extras at step 0; "
                             f"return the same extras at every step")
        if extras is None:
            return
        if not isinstance(extras, Mapping):
            raise TypeError(f"policy: extras (the second of the pair it returns) must be a dict "
                            f"of tensors{at}, got {type(extras).__name__}")
        if t and {PREFIX + k for k in extras} != set(self.extras):
            first = sorted(k[len(PREFIX):] for k in self.extras)
            raise ValueError(f"policy: extras{at} have keys {sorted(extras)}, at step 0 "
                             f"{first}; return the same keys at every step")
        for k, v in extras.items():
            if not isinstance(k, str) or not isinstance(v, torch.Tensor) or not v.ndim \
                    or v.shape[0] != self.nbatch:
                raise ValueError(f"policy: extras[{k!r}] must be a tensor nbatch x ... "
                                 f"({self.nbatch} x ...) under a str key{at}, got "
                                 f"{type(v).__name__} {tuple(getattr(v, 'shape', ()))}")
            if t:
                kept = self.extras[PREFIX + k]
                if v.shape[1:] != kept.shape[2:] or v.dtype != kept.dtype:
                    raise ValueError(f"policy: extras[{k!r}]{at} is {v.dtype} "
                                     f"{tuple(v.shape)}, at step 0 {kept.dtype} "
                                     f"{(self.nbatch, *kept.shape[2:])}; return the same "
                                     f"shape and dtype at every step")
