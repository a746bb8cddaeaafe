"""`SimDataset`: a torch `IterableDataset` of freshly simulated MuJoCo batches."""

from __future__ import annotations

import inspect
from collections.abc import Iterable, Iterator, Sequence
from typing import Any, Optional

import mujoco
import torch

from simloader import (handoff, identity, known_faults, layout, models, observe, resume,
                       sharding, streams)
from simloader import policy as simloader_policy
from simloader.backends import binding
from simloader.backends.base import Backend, Stats
from simloader.batch import Batch
from simloader.config import SimConfig, validate
from simloader.prefetch import Prefetcher


class SimDataset(torch.utils.data.IterableDataset):
    """Streams batches of `nbatch` trajectories of `nstep` steps, simulated on the fly.

    Use it with `torch.utils.data.DataLoader(ds, batch_size=None)` (each item is already a
    batch) or iterate it directly. Each item is a `simloader.batch.Batch`, a dict of tensors
    with named views (`batch.view("qpos")`, `batch.view("xpos", "hand")`); with the default
    `record`:

      =============  ==============================  ==========================================
      state          (nbatch, nframes, nstate)       mjSTATE_FULLPHYSICS state after each frame
      sensordata     (nbatch, nframes, nsensordata)  sensor values after each frame
      control        (nbatch, nstep, ncontrol)       control rows applied before each step
      initial_state  (nbatch, nstate)                state each trajectory started from
      diverged       (nbatch,) bool                  MuJoCo warning or NaN/Inf in this batch
      =============  ==============================  ==========================================

    where `nframes = nstep // record_every` (`nstep` by default). Every name of `record` is a
    key `(nbatch, nframes, *trailing shape)`.

    Args:
      model: MJCF/MJB path, MJCF XML string, `MjModel`, `MjSpec`, or a model name
        (`simloader.named_models()`: the built-in `cartpole` and `humanoid`, Gymnasium's
        `gymnasium/hopper` and the like where gymnasium is installed).
      backend: the engine: "cpu" (MuJoCo's native multithreaded CPU simulation,
        `mujoco.batch`, bit for bit `mujoco.rollout`), "mjx" (MJX on JAX: jit + vmap + scan,
        on the GPU), "warp" (MuJoCo Warp driven from torch with CUDA graphs; no JAX) or
        "auto" (the fastest of those that run here for this model, `nbatch` and machine,
        from a measured rule: `simloader.backends.auto`; `describe()` says why). The older
        spellings "rollout" and `backend="mjx", impl="jax"|"warp"|"auto"` still work and
        warn once (FutureWarning).
      nbatch: trajectories per batch.
      nstep: steps per trajectory per batch.
      control: None (inputs as `mj_resetData` leaves them, as `mujoco.rollout`), an array
        `([nbatch or 1] x [nstep or 1] x ncontrol)` used for every batch, a
        `simloader.controls` generator, or a dict `{component: generator(s)}`.
      control_spec: `mjtState` bits within `mjSTATE_USER`: the components of a control row.
      initial_state: None (model defaults), an array `([nbatch or 1] x nstate)`, a keyframe
        name, or a `simloader.initial` generator.
      randomize: None, a sequence of nbatch `MjModel` of identical sizes (trajectory i runs
        on model i), or a `simloader.randomize` spec: parameters (`dr.scale(...)`, ...) or
        `dr.Variants`; the values each trajectory runs with come back in `batch["params"]`.
      continue_episodes: each batch continues every trajectory where the previous one ended
        (solver warmstart included), so consecutive batches concatenate to one long rollout.
        A trajectory that diverged restarts from a fresh initial state in the next batch.
      num_batches: batches in total per rank (split across DataLoader workers), None: endless.
      seed: all randomness derives from it, the worker's batch indices and the rank.
      device: torch device of the delivered tensors (None: the backend's own).
      dtype: torch dtype of the floating tensors (None: float64 on the CPU engine, float32 on
        the GPU engines).
      nthread: CPU threads of the CPU engine per worker (None: the cores, or half of
        them when batches stay on the CPU beside a multi-threaded torch, split among workers
        and local ranks).
      prefetch: batches simulated ahead of the consumer.
      record: the names to record, each a batch key: "state", "sensordata", a lowercase
        mjtState component ("qpos", "qvel", "act", "time", "ctrl", "xfrc_applied", ...), any
        other MjData array field mj_step computes ("xpos", "xquat", "actuator_force", "qacc",
        "site_xpos", "ncon", ...; "cfrc_ext" where a sensor makes MuJoCo compute it), or
        "sensor:NAME". Each keeps MuJoCo's dtype (int32 and bool fields stay so).
      record_every: record after every k-th step: frame j holds the values after step
        (j + 1) * k; `nstep` must be a multiple of k. `control` still holds every step's row.
        A `simloader.Camera` in `record` renders images ("camera/NAME/rgb", ...).
      record_kinematics: what the derived fields of a frame ("xpos", "sensordata",
        "site_xpos", "actuator_force", ...) describe. "before_step" (default): as `mj_step`
        leaves them, the state the step started from (the state and images describe the
        frame itself). "frame": what `mj_forward` computes at the frame's own state (its
        inputs and warmstart as the step left them), by a forward pass after the step: the
        position and velocity stages, or all of mj_forward when a record needs the
        acceleration stage (`simloader.records.ACC_FIELDS`, acceleration sensors). The
        physics is the same either way. A policy then sees the frame's values too.
      policy: closed loop (instead of `control`): a callable, typically a `torch.nn.Module`
        on the dataset's device, called once per step, before the step, under
        `torch.no_grad()`, with a dict of the current observations (tensors `nbatch x ...`,
        keys as in `record`; at the first step those of the initial state), returning the
        control rows `(nbatch, ncontrol)` or `(control, extras)`, extras (a dict of tensors
        `nbatch x ...`) delivered as "policy/KEY" `(nbatch, nstep, ...)`. Every batch holds
        "policy/version": which update of the weights produced it (`simloader.policy.version`).
      policy_noise: exploration noise added to the policy's controls before MuJoCo's clamp: a
        `simloader.controls` generator or a dict `{component: generator(s)}`, drawn from
        `seed` as `control` is.
      deterministic: None (default): as `torch.are_deterministic_algorithms_enabled()`.
        True: the same seed gives bit-identical batches (resume and `regenerate` too) on
        every engine that can promise it for this model: the CPU engine always, MJX with
        XLA's deterministic GPU ops (set here if JAX has not started; refused, saying how,
        if it started without them), MuJoCo Warp for models where its sums cannot race (no
        contacts, at most one row per constraint type: `backends/warp/determinism.py`);
        else a ValueError naming the engine, why and the alternative. "auto" chooses among
        the engines that can. False: the fastest; GPU engines reproduce contact-rich
        trajectories only in distribution.
      sim_device: where to simulate when it is not where batches are delivered (`device`,
        which then defaults to the current CUDA device): a device ("cuda:1") or several
        (["cuda:1", "cuda:2"]); the batch's trajectories are split across them in order
        (each its own part of the stream), simulated at once, and gathered on `device` by
        peer copies that overlap the next batch's simulation. GPU engines only; a policy
        runs on a copy of its weights on each simulation device.
      terminate: episodes that end where the task ends: a rule of `simloader.terminate`
        (`Below(body, height)`, `Tilted(body, max_angle)`, `Outside(joint, low, high)`,
        `TimeLimit(steps)`), a callable `obs -> (nbatch,) bool tensor` over the observations
        a policy would get (CPU and Warp engines), or a sequence of them (any one ends the
        episode), checked at every recorded frame. After a frame whose state meets one, the trajectory's next frame is a
        fresh initial state from its `initial_state` source (autoreset; its control rows are
        delivered as NaN). The batch then holds "terminated", "truncated" (a `TimeLimit`) and
        "first" (the fresh frames), `(nbatch, nframes)` bool. None (default): every
        trajectory runs its `nstep` steps. Every engine, open or closed loop.
      **backend_options: the engine's own: `naconmax`/`njmax` for "warp" (MuJoCo Warp's
        buffers; None: sized from the model), `compilation_cache`, `memory_fraction` for
        "mjx" (see `backends.mjx.options.check_options`); with "auto", those of an engine
        not chosen are left unused. A Warp batch also holds `overflow` (nbatch,) bool:
        trajectories that lost contacts or constraint rows to those buffers.

    Raises:
      TypeError, ValueError: bad arguments, naming the argument, the expectation and the value;
        a batch that cannot fit in host memory (CPU engine), with its size.

    Warns:
      KnownFaultWarning: the model meets a known fault of the installed simulator on the
        engine chosen (`simloader.known_faults`), naming it, the version that fixes it and the
        model setting that avoids it; once per fault and model per process.
    """

    def __init__(self, model: Any, *, backend: str = "auto", nbatch: int, nstep: int,
                 control: Any = None, control_spec: int = int(mujoco.mjtState.mjSTATE_CTRL),
                 initial_state: Any = None, randomize: Any = None,
                 continue_episodes: bool = False, num_batches: Optional[int] = None,
                 seed: int = 0, device: Any = None, dtype: Any = None,
                 nthread: Optional[int] = None, prefetch: int = 2,
                 record: Sequence[str] = observe.DEFAULT, record_every: int = 1,
                 policy: Any = None, policy_noise: Any = None,
                 deterministic: Optional[bool] = None, sim_device: Any = None,
                 terminate: Any = None, record_kinematics: str = "before_step",
                 **backend_options: Any):
        super().__init__()
        # what it was made with, for `reseeded`
        self._arguments = {**{k: v for k, v in locals().items()
                              if k not in ("self", "__class__", "backend_options")},
                           **backend_options}
        binding.check_keywords(backend_options, _KEYWORDS)
        settings, parts = validate(
            model, nbatch=nbatch, nstep=nstep, control=control, control_spec=control_spec,
            initial_state=initial_state, randomize=randomize,
            continue_episodes=continue_episodes, num_batches=num_batches, seed=seed,
            device=device, dtype=dtype, nthread=nthread, prefetch=prefetch, record=record,
            record_every=record_every, policy=policy, policy_noise=policy_noise,
            deterministic=deterministic, sim_device=sim_device, terminate=terminate,
            record_kinematics=record_kinematics)
        self.engine: binding.BoundEngine = binding.bind(backend, backend_options, settings,
                                                        parts)
        self.config: SimConfig = self.engine.config
        known_faults.warn_once(self.config.pool, self.config.backend)
        plan = self.config.randomization
        self.layout = layout.BatchLayout(self.config.model, self.config.control_spec,
                                         self.config.observations,
                                         plan.columns if plan is not None else None)
        self.source = models.source(model)  # where the model came from, for describe()
        self._stats = Stats.of(self.engine.counters)
        # workers do not see the process group: keep the rank of the constructing process
        self._rank = sharding.distributed_rank()
        # where the iterator is: progress (shard, next index, backend, produced, stream tags)
        self._position = resume.Position()

    @property
    def model(self) -> mujoco.MjModel:
        return self.config.model

    @property
    def stats(self) -> dict[str, Any]:
        """Counters of the iterators run in this process (workers keep their own), and the
        engine that simulates (`backend`: "cpu", "mjx" or "warp")."""
        out = self._stats.as_dict()
        out["backend"] = self.config.backend
        return out

    def describe(self) -> str:
        """Where the model came from, which columns of state, control and sensors mean what (by
        object name), the recorded keys with the named parts `Batch.view` finds in them, what
        simulates, and the known faults of that simulator the model meets
        (`simloader.known_faults`; each also warned once at construction, `KnownFaultWarning`);
        once batches were delivered in this process, where their time went (`time_spent`)."""
        c = self.config
        text = (layout.describe(c.model, c.control_spec, self.source)
                + f"\nrecorded keys (nbatch, nframes={c.nframes}, ...), every "
                  f"{c.record_every} step(s):\n" + self.layout.describe())
        if c.variants is not None:
            text += ("\nrandomized: batch[\"params\"] keys, the values each trajectory ran "
                     f"with:\n  variant ({c.nbatch},): the index of its variant")
        elif self.layout.params:
            text += ("\nrandomized: batch[\"params\"] keys (batch.view(KEY, NAME) finds a "
                     "column), the values each trajectory ran with:\n"
                     + layout.describe_params(self.layout.params, c.nbatch))
        where = ""
        if c.parts is not None:
            where = (f"; simulated on {', '.join(str(p.device) for p in c.parts)} (trajectories "
                     f"{', '.join(str(p.nbatch) for p in c.parts)}), delivered on {c.device}")
        exact = "; deterministic: bit-identical batches for the same seed" if c.deterministic \
            else ""
        return text + (f"\nsimulated by: backend={c.backend!r} ({c.options.simulated_by()}; "
                       f"chosen: {c.backend_reason}{where}{exact})") + "".join(
            "\n" + line for line in known_faults.described(c.pool, c.backend)) + \
            self.time_spent()

    def time_spent(self) -> str:
        """A line saying where this process's iterators spent their time (`stats`: DataLoader
        workers count their own); "" before a first batch."""
        s = self.stats
        if not s["batches"]:
            return ""
        # and the engine's own seconds (MJX: compile_s, trace_s), by their names
        seconds = [f"{s['simulate_s']:.2f} s simulating ({s['steps_per_s'] / 1e6:.3g}M "
                   f"steps/s)"] + [f"{v:.2f} s {k.removesuffix('_s').replace('_', ' ')}"
                                   for k, v in self._stats.own.items()
                                   if k.endswith("_s") and v]
        return (f"\nso far in this process: {s['batches']} batches, {s['steps']:,} steps, "
                f"{s['diverged']} diverged trajectories; {', '.join(seconds)}")

    def __len__(self) -> int:
        if self.config.num_batches is None:
            raise TypeError("SimDataset with num_batches=None is endless and has no len()")
        return self.config.num_batches

    def reseeded(self, seed: int) -> "SimDataset":
        """The same dataset with another `seed` (a new dataset: its stream starts afresh)."""
        return SimDataset(**{**self._arguments, "seed": seed})

    def make_backend(self, shard: Optional[sharding.Shard] = None) -> Backend:
        """The backend for a shard (default: the calling process's), e.g. to benchmark it."""
        shard = shard or sharding.current_shard(self._rank)
        with handoff.current_device_kept():  # the caller's device is its own
            return self.engine.create(shard, self._stats)

    def state_dict(self) -> dict[str, Any]:
        """Where this iterator (this DataLoader worker, or this process) is in the stream.

        Small and JSON-serializable; usable by torchdata's `StatefulDataLoader`. Loading it into
        a dataset of the same configuration resumes exactly after the last delivered batch
        (the stream keys' episode counters too: `simloader.streams`).
        """
        saved = self._position.saved(lambda: {
            "version": resume.VERSION, "config": identity.fingerprint(self.config),
            "shard": None, "next_index": None, "trajectories": None, "streams": None})
        if saved is not None:  # nothing delivered since the last load or iter()
            return saved
        shard, next_index, backend, produced, tags = self._position.progress
        return {"version": resume.VERSION,
                "config": identity.fingerprint(self.config),
                "shard": [shard.worker, shard.num_workers, shard.rank],
                "next_index": next_index, "trajectories": backend.checkpoint(produced),
                "streams": tags.state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resumes the stream saved by `state_dict()` at the next iteration.

        Raises:
          ValueError: the state belongs to a stream of another configuration.
        """
        resume.check(self.config, state)
        self._position.load(state)

    def __iter__(self) -> Iterator[Batch]:
        if self.config.policy is not None:
            simloader_policy.check_worker(self.config.policy)
        shard = sharding.current_shard(self._rank)
        return self._batches(shard, self._position.start(shard, "next_index"))

    def _batches(self, shard: sharding.Shard,
                 loaded: Optional[dict]) -> Iterator[dict[str, torch.Tensor]]:
        backend = self.make_backend(shard)
        start = None
        if loaded is not None:
            start = loaded["next_index"]
            if loaded["trajectories"] is not None:
                with handoff.current_device_kept():
                    backend.restore(loaded["trajectories"])
        tags = streams.StreamTags(shard, self.config.nbatch, self.config.continue_episodes,
                                  None if loaded is None else loaded.get("streams"))
        for index, batch, produced in self.stream(
                backend, shard.indices(self.config.num_batches, start)):
            tags.tag(batch)
            self._position.progress = (shard, index + shard.num_workers, backend, produced,
                                       tags)
            yield batch

    def batches_at(self, indices: Iterable[int], shard: Optional[sharding.Shard] = None
                   ) -> Iterator[tuple[int, Batch]]:
        """(index, batch) for each global batch index of `indices`, as a shard (default: the
        calling process's) streams it, simulated `prefetch` batches ahead: the producer the
        store calls (`write` fills the slots it chose; `regenerate` replays a stream up to a
        stored batch). The indices need not follow the shard's own order."""
        stream = self.stream(self.make_backend(shard), indices)
        try:
            for index, batch, _ in stream:
                yield index, batch
        finally:  # closed with it: the prefetch thread and the backend end now
            stream.close()

    def stream(self, backend: Backend, indices: Iterable[int]) -> Iterator[tuple]:
        """(index, batch, what the backend produced) for each global batch index, simulated
        `prefetch` batches ahead in a thread; closes the backend at the end. For `write` and
        the regeneration of stored trajectories, which choose their own indices."""
        prefetcher = Prefetcher(lambda i: (i, backend.produce(i)), indices,
                                self.config.prefetch, at_exit=backend.close)
        try:
            for index, produced in prefetcher:
                with handoff.current_device_kept():  # the consumer's device is its own
                    delivered = backend.deliver(produced)
                yield index, Batch(delivered, layout=self.layout), produced
        finally:
            # (no device guard here: this also runs at interpreter exit, on a generator left
            # open, when the modules it would call may be gone)
            prefetcher.close()
            backend.close()


# SimDataset's own keywords: an unknown keyword close to one of them is a typo
_KEYWORDS = tuple(n for n, p in inspect.signature(SimDataset.__init__).parameters.items()
                  if p.kind == inspect.Parameter.KEYWORD_ONLY)
