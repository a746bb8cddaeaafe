"""What an engine offers the registry: the `Engine` protocol, and what `auto` asks of it.

An engine lives in a package of its own whose light entry module (`entry.py`: no JAX, no Warp,
no CUDA at import) holds an `Engine`; the registry (`backends/__init__.py`) maps the engine's
`backend=` word to that module and calls nothing else. An engine from outside simloader joins
with `simloader.backends.register_engine(engine)`. `tests/test_engines.py` checks every
built-in entry against the protocol and streams batches through an engine registered from
outside the package.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Optional, Protocol, runtime_checkable


@dataclasses.dataclass(frozen=True)
class Job:
    """What `backend="auto"` asks every engine to estimate its steps/s for.

    Attributes:
      step_s: the model's `mj_step` time on one CPU core (`auto.cpu_step_seconds`).
      nbatch: trajectories per batch.
      contacts: whether any two geoms of the model may collide.
      cores: the CPU cores this process may use.
      policy: whether a policy picks every step's controls (`policy=`).
      cameras: whether the batch records images (`simloader.Camera`).
      steps: the steps this process will simulate (`nbatch * nstep * num_batches`), or None
        for an endless stream: with a known length, an engine's start-up counts too.
      episodes: whether episodes end on rules (`terminate=`), with autoreset.
      episode_callable: whether a callable over the observations ends them (it runs in
        Python after every frame).
    """

    step_s: float
    nbatch: int
    contacts: bool
    cores: int
    policy: bool
    cameras: bool
    steps: Optional[int] = None
    episodes: bool = False
    episode_callable: bool = False


@runtime_checkable
class Engine(Protocol):
    """An engine as the registry sees it.

    Attributes:
      name: its `backend=` word.
      options: the keyword options of `SimDataset` it takes (a dataset passes only these).
      counters: its own counters in `SimDataset.stats` (besides every engine's).
    """

    # read-only: an engine may hold them as class attributes of narrower types (a tuple of
    # two names), which a type checker accepts for a read-only member only
    @property
    def name(self) -> str: ...

    @property
    def options(self) -> tuple[str, ...]: ...

    @property
    def counters(self) -> tuple[str, ...]: ...


    @property
    def forks_safely(self) -> bool:
        """Whether a DataLoader worker forked from the constructing process may run it (no
        GPU runtime, no JAX, no OpenGL in its state); else workers are spawned."""

    def missing(self) -> Optional[str]:
        """Why it cannot run in this process (what to install, what hardware), or None; fast,
        starts nothing (no JAX, no CUDA context)."""

    def confirm(self) -> Optional[str]:
        """The thorough form of `missing`, which may start the engine's runtime (JAX asked
        for its GPUs); called only for the engine `auto` is about to choose."""

    def estimate(self, job: Job) -> Optional[float]:
        """Its steps/s for `job`, from a measured rule, for `backend="auto"`; None: it cannot
        simulate this job (e.g. cameras on an engine that does not render)."""

    def startup_s(self, job: Job) -> float:
        """Its estimated seconds to the first batch (compilation, kernels), for `auto` on a
        stream of known length."""

    def prepare(self, options: dict[str, Any]) -> None:
        """Process-wide settings that must precede anything that may start its runtime (the
        `auto` choice included): for MJX, how JAX takes GPU memory."""

    def check_sizes(self, sizes: Any) -> None:
        """Refuses a batch too large for it from its sizes alone (before tables are built)."""

    def refuses_sim_device(self) -> Optional[str]:
        """Why `sim_device=` cannot name devices for it (it simulates on no torch device of
        its own), or None where it can."""

    def refuses_model(self, model: Any) -> Optional[str]:
        """Why it cannot simulate `model`, naming the feature and the objects (geoms, bodies)
        that use it, or None when it can. Asked by `auto` of the engine it is about to choose
        (one that refuses is passed over, and `backend_reason` says why), of an engine asked
        by name before it builds anything, and by `simloader info`; no runtime is started
        for it."""

    def refuses_determinism(self, model: Any) -> Optional[str]:
        """Why it cannot give bit-identical batches for `model` from the same seed (with what
        to use instead), or None when it can. A question, asked for `deterministic=True`
        before its runtime starts, with no side effect: what makes it deterministic (MJX:
        XLA's deterministic GPU ops) is set where its runtime starts (`check_options`, for a
        configuration with `deterministic`)."""

    def check_options(self, config: Any, options: dict[str, Any], reason: str) -> Any:
        """Validates the settings (`config.Settings`: everything but the engine's own fields)
        and its options at construction; returns its resolved options (a frozen dataclass
        with `simulated_by() -> str`; its compared fields enter the configuration's identity,
        `identity.fingerprint`)."""

    def create(self, config: Any, shard: Any, stats: Any) -> Any:
        """Its `Backend` (`backends.base`) for one shard, in the process that iterates."""


class EngineEntry:
    """Defaults for an `Engine` (subclass it and fill in the rest): runs everywhere, needs no
    process-wide settings, no size limit of its own, never chosen by `auto`, promises no
    bit-identical batches."""

    name: str = ""
    options: tuple[str, ...] = ()
    counters: tuple[str, ...] = ()
    forks_safely: bool = False

    def missing(self) -> Optional[str]:
        return None

    def confirm(self) -> Optional[str]:
        return self.missing()

    def estimate(self, job: Job) -> Optional[float]:
        return None

    def startup_s(self, job: Job) -> float:
        return 0.0

    def prepare(self, options: dict[str, Any]) -> None:
        return None

    def check_sizes(self, sizes: Any) -> None:
        return None

    def refuses_sim_device(self) -> Optional[str]:
        return f"backend={self.name!r} simulates on no device of its own"

    def stored_renderer(self, model: Any, images: Any, device: Any,
                        randomized: bool) -> Any:
        """A renderer of stored states for `StoredDataset(cameras=)` (`store/pixels.py`):
        an object whose `frames(states, model_of)` renders `(n, nframes, nstate)`
        mjSTATE_FULLPHYSICS states, trajectory i with `model_of(i)`, as this engine's
        streamed cameras render them, into `{image key: (n, nframes, *shape) tensor}` on
        `device`. `randomized`: trajectories have models of their own. Raises ValueError
        naming what it cannot render; this default renders nothing."""
        raise ValueError(f"backend={self.name!r} does not render stored states")

    def refuses_model(self, model: Any) -> Optional[str]:
        return None

    def refuses_determinism(self, model: Any) -> Optional[str]:
        return (f"backend={self.name!r} does not promise bit-identical batches; "
                f"backend='cpu' does")
