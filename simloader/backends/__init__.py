"""The simulation engines behind `SimDataset`, and how one is chosen.

`backend="rollout"` is MuJoCo on CPU threads (`cpu/`). `backend="mjx"` is a GPU engine
picked by `impl`: `"jax"` (MJX on JAX, `mjx/`) or `"warp"` (MuJoCo Warp driven from torch,
`warp/`). The dataset talks to engines only through this registry: resolve "auto", validate an
engine's options, create one for a shard. Engine modules are imported when first needed, so
that a CPU-only user never imports JAX, and a Warp dataset never imports JAX either.
"""

from __future__ import annotations

import dataclasses
import glob
import importlib
import importlib.util
from collections.abc import Callable
from typing import Any, Optional

import mujoco
import numpy as np

from simloader import observe, sharding
from simloader.backends.base import Backend, Stats
from simloader.config import SimConfig

BACKENDS = ("auto", "rollout", "mjx")
IMPLS = ("auto", "jax", "warp")
# Each engine's package by its `impl` (the CPU backend's is "c"), imported when first needed.
# Every package offers the same two entry points: `check_options(config, options, reason)`
# returns its resolved options (with `impl`), `create(config, shard, stats)` its backend. The
# registry decides which engine runs; it never branches on an engine's name to call it.
ENGINES = {"c": "simloader.backends.cpu", "jax": "simloader.backends.mjx",
           "warp": "simloader.backends.warp"}
# backend="mjx" options beyond `impl`, by engine, known here without importing the engines
# (for SimDataset's did-you-mean): MuJoCo Warp's buffers, JAX's caches and memory
ENGINE_OPTIONS = {"warp": ("naconmax", "njmax"), "jax": ("compilation_cache", "memory_fraction")}
OPTIONS = ("impl",) + tuple(name for names in ENGINE_OPTIONS.values() for name in names)


def engine(impl: str) -> Any:
    """The package of the engine `impl` (a key of `ENGINES`), imported now."""
    return importlib.import_module(ENGINES[impl])


def _mjx_installed() -> bool:
    return importlib.util.find_spec("mujoco.mjx") is not None


def prepare(backend: Any, options: dict[str, Any]) -> None:
    """Process-wide settings that must precede JAX's start, applied before the configuration
    is validated (`backend="auto"` may ask JAX for its devices): JAX's GPU memory. With
    `backend="mjx"` JAX's own checks set it first (`mjx.check_options`); nothing for a dataset
    that asks for the Warp engine."""
    if options.get("impl") == "warp":
        return
    if backend == "auto" and _mjx_installed() and _gpu_visible():
        from simloader.backends.mjx import runtime
        runtime.configure_memory(options.get("memory_fraction"))


def _gpu_visible() -> bool:
    """Whether this machine may have a GPU for JAX, decided without starting JAX: an NVIDIA
    device node, or torch seeing CUDA."""
    if glob.glob("/dev/nvidia[0-9]*"):
        return True
    import torch
    return torch.cuda.is_available()


def resolve(backend: Any, options: Optional[dict[str, Any]] = None) -> str:
    """"auto" is "mjx" when a GPU engine can run (MuJoCo Warp and a CUDA GPU, or MJX installed
    and JAX seeing a GPU), else "rollout"; JAX starts only to ask for its GPUs where MuJoCo
    Warp cannot run and a GPU may be.

    Raises:
      TypeError, ValueError: not one of `BACKENDS`.
    """
    if not isinstance(backend, str):
        raise TypeError(f"backend: expected one of {BACKENDS}, got {type(backend).__name__}")
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if backend != "auto":
        return backend
    from simloader.backends.warp import runtime as warp_runtime
    import torch
    if warp_runtime.missing() is None and torch.cuda.is_available():
        return "mjx"  # a GPU engine runs; which one, `choose` decides (without JAX if Warp)
    if (options or {}).get("impl") == "warp":
        return "rollout"
    if not (_mjx_installed() and _gpu_visible()):
        return "rollout"
    prepare(backend, {})  # JAX starts here: without preallocation unless told otherwise
    try:
        import jax
        return "mjx" if any(d.platform == "gpu" for d in jax.devices()) else "rollout"
    except Exception:  # JAX without a usable platform
        return "rollout"


@dataclasses.dataclass(frozen=True)
class Choice:
    """The GPU engine a dataset runs, and why (shown by `describe()` and in `stats`)."""

    impl: str
    reason: str


def choose(asked: Any, config: SimConfig) -> Choice:
    """Resolves `impl`: "jax" and "warp" as asked; "auto" the faster one available.

    Measured on an H200 (benchmarks/results): MuJoCo Warp is 2.5x MJX-JAX on the humanoid
    (contacts, a constraint solver with many rows), while on a contact-free model JAX's fused
    XLA step is faster (cart-pole 8192: 36.7M vs 29.0M steps/s). So "auto" takes Warp, where
    it can run, for a model with contacts, for cameras (only MuJoCo Warp renders) and for a
    policy in the loop (one CUDA graph replay per step against a jitted step per call), and
    JAX otherwise. Decided without starting JAX.

    Raises:
      TypeError: `impl` is not a string.
      ValueError: `impl` is unknown.
    """
    if not isinstance(asked, str):
        raise TypeError(f"impl: expected one of {IMPLS}, got {type(asked).__name__} {asked!r}")
    if asked not in IMPLS:
        raise ValueError(f"impl: expected one of {IMPLS}, got {asked!r}")
    if asked != "auto":
        return Choice(asked, "asked")
    from simloader.backends.warp import runtime as warp_runtime
    missing = warp_runtime.missing()
    if missing:
        return Choice("jax", f"auto: {missing}")
    if any(isinstance(o, observe.CameraImage) for o in config.observations):
        return Choice("warp", "auto: cameras render only on MuJoCo Warp")
    if config.policy is not None:
        return Choice("warp", "auto: a policy in the loop runs fastest on MuJoCo Warp's CUDA "
                              "graph per step")
    if has_contacts(config.model):
        return Choice("warp", "auto: the model has contacts, where MuJoCo Warp is faster")
    return Choice("jax", "auto: the model has no contacts, where MJX-JAX is faster")


def has_contacts(model: mujoco.MjModel) -> bool:
    """Whether any two geoms may collide (explicit pairs, or contype/conaffinity filtering of
    geoms on different bodies), unless contacts are disabled."""
    if model.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    if model.npair:
        return True
    body = model.geom_bodyid
    contype, conaffinity = model.geom_contype, model.geom_conaffinity
    mask = ((contype[:, None] & conaffinity[None, :]) | (conaffinity[:, None] & contype[None, :]))
    mask = (mask != 0) & (body[:, None] != body[None, :])
    return bool(np.triu(mask, 1).any())


def size_check(backend: str) -> Optional[Callable[[Any], None]]:
    """The resolved `backend`'s refusal of a batch too large for it, from its sizes alone
    (`config.build_config` calls it before building tables): the CPU engine's check of host
    memory. None for `"mjx"`: its engines check their device's memory once they have the
    device (`check_options`, `create`)."""
    return engine("c").check_sizes if backend == "rollout" else None


def check_options(config: SimConfig, asked: str, options: dict[str, Any]) -> Any:
    """Validates engine-specific keyword options at construction (`asked`: the `backend`
    argument before "auto" was resolved); returns them resolved by the chosen engine, for
    `SimConfig.options`."""
    if config.backend == "mjx":
        unknown = sorted(set(options) - set(OPTIONS))
        if unknown:
            raise TypeError(f"SimDataset: unexpected keyword argument(s) {unknown} for "
                            f"backend='mjx' (its options are {list(OPTIONS)})")
        choice = choose(options.get("impl", "auto"), config)
        return engine(choice.impl).check_options(config, options, choice.reason)
    if "impl" in options and asked == "auto":
        raise ValueError(
            f"impl: {options['impl']!r} chooses the GPU engine, but backend='auto' resolved to "
            f"'rollout' here (no GPU visible, or the engine's packages missing); pass "
            f"backend='mjx' to run it anyway")
    return engine("c").check_options(config, options, "backend='rollout'")


def create(config: SimConfig, shard: sharding.Shard, stats: Stats) -> Backend:
    """The engine of `config` (its resolved options say which) for one shard."""
    return engine(config.options.impl).create(config, shard, stats)
