"""The simulation engines behind `SimDataset`, and how one is chosen.

`backend="cpu"` is MuJoCo on CPU threads (`cpu/`), `backend="mjx"` MJX on JAX (`mjx/`),
`backend="warp"` MuJoCo Warp driven from torch, without JAX (`warp/`), and `backend="auto"`
the fastest of those that can run here for the model, the sizes and the machine (`auto.py`).
The dataset talks to engines only through this registry: name the engine, validate its
options, create one for a shard. Engine packages are imported when first needed, so that a
CPU-only user never imports JAX, and a Warp dataset never imports JAX either.

The older spellings (`backend="rollout"`; `backend="mjx", impl="jax"|"warp"|"auto"`) keep
working and warn once with the new one (`spelled`).
"""

from __future__ import annotations

import glob
import importlib
import importlib.util
import warnings
from collections.abc import Callable
from typing import Any, Optional

from simloader import sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig

# each engine's package, imported when first needed; every package offers the same entry
# points: `check_options(config, options, reason)` returns its resolved options,
# `create(config, shard, stats)` its backend
ENGINES = {"cpu": "simloader.backends.cpu", "mjx": "simloader.backends.mjx",
           "warp": "simloader.backends.warp"}
BACKENDS = ("auto",) + tuple(ENGINES)
# each engine's own keyword options, known here without importing the engines (for
# SimDataset's did-you-mean and for refusing another engine's option by name)
ENGINE_OPTIONS = {"cpu": (), "mjx": ("compilation_cache", "memory_fraction"),
                  "warp": ("naconmax", "njmax")}
# `impl` is the older spelling of the engine (see `spelled`)
OPTIONS = ("impl",) + tuple(name for names in ENGINE_OPTIONS.values() for name in names)
# the older spellings: backend="rollout", and backend="mjx" with impl=
_OLD_IMPLS = {"jax": "mjx", "warp": "warp", "auto": "auto"}
_warned: set[str] = set()


def engine(name: str) -> Any:
    """The package of the engine `name` (a key of `ENGINES`), imported now."""
    return importlib.import_module(ENGINES[name])


def _warn_once(old: str, new: str) -> None:
    if old not in _warned:
        _warned.add(old)
        # stacklevel: the user's line (SimDataset.__init__, here)
        warnings.warn(f"{old} is the older spelling of {new}; it still works for now and will "
                      f"be removed", FutureWarning, stacklevel=4)


def spelled(backend: Any, options: dict[str, Any]) -> tuple[str, dict[str, Any], bool]:
    """The `backend` argument in today's vocabulary: (backend, options without `impl`,
    whether only GPU engines may be chosen). The older spellings warn once per process
    (FutureWarning) naming the new one.

    Raises:
      TypeError, ValueError: `backend` not one of `BACKENDS`; `impl` not one of "jax",
        "warp", "auto", or given with a backend other than "mjx".
    """
    if not isinstance(backend, str):
        raise TypeError(f"backend: expected one of {BACKENDS}, got {type(backend).__name__} "
                        f"{backend!r}")
    if backend == "rollout":
        _warn_once("backend='rollout'", "backend='cpu'")
        backend = "cpu"
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
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


def _gpu_visible() -> bool:
    """Whether this machine may have a GPU, decided without starting JAX or CUDA: an NVIDIA
    device node, or torch seeing CUDA."""
    if glob.glob("/dev/nvidia[0-9]*"):
        return True
    import torch
    return torch.cuda.is_available()


def mjx_installed() -> bool:
    return importlib.util.find_spec("mujoco.mjx") is not None


def prepare(backend: str, options: dict[str, Any]) -> None:
    """Process-wide settings that must precede JAX's start, applied before anything may ask
    JAX for its devices: JAX's GPU memory, for a dataset that may run MJX."""
    if backend in ("auto", "mjx") and mjx_installed() and _gpu_visible():
        from simloader.backends.mjx import runtime
        runtime.configure_memory(options.get("memory_fraction"))


def size_check(backend: str) -> Optional[Callable[[Any], None]]:
    """The engine's refusal of a batch too large for it, from its sizes alone
    (`config.build_config` calls it before building tables): the CPU engine's check of host
    memory. None for the GPU engines: they check their device's memory once they have the
    device (`check_options`, `create`)."""
    return engine("cpu").check_sizes if backend == "cpu" else None


def check_options(config: SimConfig, reason: str, options: dict[str, Any]) -> Any:
    """Validates engine-specific keyword options at construction; returns them resolved by
    the engine `config.backend` (chosen for `reason`), for `SimConfig.options`.

    Raises:
      TypeError: an option of another engine, or none at all, naming this engine's options.
    """
    mine = ENGINE_OPTIONS[config.backend]
    unknown = sorted(set(options) - set(mine))
    if unknown:
        # with backend="auto" an option of an engine that was not chosen is left unused
        # (the user may not know which engine runs); asked by name, it is a mistake
        asked = "auto" not in reason
        if asked or any(name not in OPTIONS for name in unknown):
            owners = [f"{n!r} is an option of backend={e!r}" for n in unknown
                      for e, names in ENGINE_OPTIONS.items() if n in names]
            raise TypeError(f"SimDataset: unexpected keyword argument(s) {unknown} for "
                            f"backend={config.backend!r} (its options are {list(mine)})"
                            + "".join(f"; {o}" for o in owners))
        options = {k: v for k, v in options.items() if k in mine}
    return engine(config.backend).check_options(config, options, reason)


def create(config: SimConfig, shard: sharding.Shard, stats: Stats) -> Backend:
    """The engine of `config` for one shard."""
    return engine(config.backend).create(config, shard, stats)
