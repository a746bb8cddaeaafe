"""The simulation engines behind `SimDataset`, and how one is chosen.

`backend="cpu"` is MuJoCo on CPU threads (`cpu/`), `backend="mjx"` MJX on JAX (`mjx/`),
`backend="warp"` MuJoCo Warp driven from torch, without JAX (`warp/`), and `backend="auto"`
the fastest of those that can run here for the model, the sizes and the machine (`auto.py`).
Construction meets the registry once: `binding.bind` chooses the engine and binds it to the
validated settings; the dataset then holds the `BoundEngine` and calls it directly. Engine
packages are imported when first needed, so that a CPU-only user never imports JAX, and a
Warp dataset never imports JAX either.

The older spellings (`backend="rollout"`; `backend="mjx", impl="jax"|"warp"|"auto"`) keep
working and warn once with the new one (`spelled`).
"""

from __future__ import annotations

import glob
import importlib
import warnings
from typing import Any

from simloader import identity
from simloader.backends.contract import Engine

# each engine's light entry module (its `ENGINE`, an `Engine` of `contract.py`), imported when
# first needed; engines from outside simloader join with `register_engine`
ENGINES: dict[str, Any] = {"cpu": "simloader.backends.cpu.entry",
                           "mjx": "simloader.backends.mjx.entry",
                           "warp": "simloader.backends.warp.entry"}
# the older spellings, the one table of them: backend="rollout", and backend="mjx" (or
# "auto") with impl= (`spelled` for new datasets, `old_spelling` for saved fingerprints)
OLD_BACKENDS = {"rollout": "cpu"}
_OLD_IMPLS = {"jax": "mjx", "warp": "warp", "auto": "auto"}
# saved fingerprints (a state_dict, a store's provenance) in those spellings are the same
# streams: `identity.upgraded` reads them in today's words
identity.OLD_SPELLINGS.update({(old, None): new for old, new in OLD_BACKENDS.items()})
identity.OLD_SPELLINGS.update({("mjx", impl): new for impl, new in _OLD_IMPLS.items()
                               if new != "auto"})
_warned: set[str] = set()


def engine(name: str) -> Engine:
    """The registered engine `name` (a key of `ENGINES`), its entry module imported now."""
    entry = ENGINES[name]
    if isinstance(entry, str):
        entry = ENGINES[name] = importlib.import_module(entry).ENGINE
    return entry


def register_engine(new: Engine) -> None:
    """Adds an engine from outside simloader: `SimDataset(backend=new.name)` then runs it,
    and `backend="auto"` weighs its `estimate` against the others'.

    Raises:
      TypeError: `new` does not offer the `Engine` protocol (`backends.contract`).
      ValueError: its name is taken or not a plain word.
    """
    if not isinstance(new, Engine):
        raise TypeError(f"engine: expected an object with the Engine protocol's attributes "
                        f"(simloader.backends.contract.Engine), got {type(new).__name__}")
    if not isinstance(new.name, str) or not new.name.isidentifier() or new.name in (
            "auto", *OLD_BACKENDS) or new.name in ENGINES:
        raise ValueError(f"engine: name {new.name!r} is taken or not a plain word (taken: "
                         f"{backends()})")
    ENGINES[new.name] = new


def unregister_engine(name: str) -> None:
    """Removes an engine `register_engine` added (the built-in ones stay)."""
    if name in ("cpu", "mjx", "warp"):
        raise ValueError(f"engine: {name!r} is built in")
    ENGINES.pop(name, None)


def backends() -> tuple[str, ...]:
    """Every word `backend=` takes: "auto" and the registered engines."""
    return ("auto",) + tuple(ENGINES)


def engine_options() -> dict[str, tuple[str, ...]]:
    """Each engine's own keyword options, by engine."""
    return {name: tuple(engine(name).options) for name in ENGINES}


def all_options() -> tuple[str, ...]:
    """Every engine's keyword options, and `impl` (the older spelling of the engine)."""
    return ("impl",) + tuple(dict.fromkeys(n for names in engine_options().values()
                                           for n in names))


def _warn_once(old: str, new: str) -> None:
    if old not in _warned:
        _warned.add(old)
        # stacklevel: the user's line (_warn_once, spelled, binding.bind, SimDataset.__init__,
        # the user)
        warnings.warn(f"{old} is the older spelling of {new}; it still works for now and will "
                      f"be removed", FutureWarning, stacklevel=5)


def spelled(backend: Any, options: dict[str, Any]) -> tuple[str, dict[str, Any], bool]:
    """The `backend` argument in today's vocabulary: (backend, options without `impl`,
    whether only GPU engines may be chosen). The older spellings warn once per process
    (FutureWarning) naming the new one.

    Raises:
      TypeError, ValueError: `backend` not one of `backends()`; `impl` not one of "jax",
        "warp", "auto", or given with a backend other than "mjx".
    """
    if not isinstance(backend, str):
        raise TypeError(f"backend: expected one of {backends()}, got {type(backend).__name__} "
                        f"{backend!r}")
    if backend in OLD_BACKENDS:
        _warn_once(f"backend={backend!r}", f"backend={OLD_BACKENDS[backend]!r}")
        backend = OLD_BACKENDS[backend]
    if backend not in backends():
        raise ValueError(f"backend: expected one of {backends()}, got {backend!r}")
    if "impl" not in options:
        return backend, options, False
    options = dict(options)
    impl = options.pop("impl")
    if not isinstance(impl, str) or impl not in _OLD_IMPLS:
        raise ValueError(f"impl: the older spelling of backend=, expected one of "
                         f"{tuple(_OLD_IMPLS)} or none, got {impl!r}")
    if backend not in ("mjx", "auto"):
        raise ValueError(f"impl: {impl!r} is the older way to name a GPU engine and means "
                         f"nothing with backend={backend!r}; drop it")
    new = _OLD_IMPLS[impl]
    _warn_once(f"backend={backend!r}, impl={impl!r}", f"backend={new!r}")
    return new, options, impl == "auto"


def acceptance(model: Any) -> list[str]:
    """One line per registered engine: whether it simulates `model` ("accepts"), or why not
    ("refuses: ..." naming the feature and the objects; "cannot run here: ..."), for
    `simloader info`. An engine that cannot run here is not asked about the model."""
    lines = []
    for name in ENGINES:
        entry = engine(name)
        why = entry.missing()
        if why is not None:
            lines.append(f"{name}: cannot run here ({why})")
            continue
        refusal = entry.refuses_model(model)
        lines.append(f"{name}: accepts" if refusal is None else f"{name}: refuses: {refusal}")
    return lines


def on_devices() -> tuple[str, ...]:
    """The registered engines that simulate on a device of their own (a GPU: those
    `sim_device=` may place; `simloader warmup` compiles them)."""
    return tuple(name for name in ENGINES if engine(name).refuses_sim_device() is None)


def gpu_visible() -> bool:
    """Whether this machine may have a GPU, decided without starting JAX or CUDA: an NVIDIA
    device node, or torch seeing CUDA."""
    if glob.glob("/dev/nvidia[0-9]*"):
        return True
    import torch
    return torch.cuda.is_available()


def prepare(backend: str, options: dict[str, Any]) -> None:
    """Process-wide settings that must precede anything that may start an engine's runtime
    (`auto` may ask JAX for its GPUs): each engine that may run this dataset sets its own."""
    for name in (ENGINES if backend == "auto" else [backend]):
        engine(name).prepare(options)


# `StoredDataset(cameras=, backend="auto")`: the engine that renders stored states where the
# images are delivered (a CUDA device: MuJoCo Warp's renderer; the host: the CPU engine's)
_RENDERS_ON = {"cuda": "warp", "cpu": "cpu"}


def stored_renderer(backend: str, model: Any, images: Any, device: Any,
                    randomized: bool) -> Any:
    """The renderer of stored states of engine `backend` ("auto": by `device`'s type, the
    host without one), from the engine's `stored_renderer`.

    Raises:
      ValueError: an unknown engine, or one that cannot render them here (it says why).
    """
    import torch
    if backend == "auto":
        kind = torch.device(device).type if device is not None else "cpu"
        backend = _RENDERS_ON.get(kind, "cpu")
    if backend not in ENGINES:
        raise ValueError(f"backend: expected 'auto' or one of {list(ENGINES)} to render "
                         f"stored states, got {backend!r}")
    chosen = engine(backend)
    why = chosen.missing()
    if why is not None:
        raise ValueError(f"backend={backend!r} cannot render stored states here: {why}")
    return chosen.stored_renderer(model, images, device, randomized)
