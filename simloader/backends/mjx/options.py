"""MJX's options and its checks at construction: the user's options (JAX's compilation cache,
its GPU memory), and what MJX cannot simulate, record or randomize, refused by name.

The checks run in the constructing process and put the models on the device
(`program.Placed`), which the first program of that process reuses.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from typing import Any, Optional

import jax
import numpy as np
import torch

from simloader import memory, observe
from simloader.backends.mjx import observe as mjx_observe
from simloader.backends.mjx import randomize as mjx_randomize
from simloader.backends.mjx import runtime
from simloader.backends.mjx.program import Placed
from simloader.config import SimConfig


@dataclasses.dataclass(frozen=True)
class MjxOptions:
    """MJX's options, validated and resolved at construction.

    Attributes:
      compilation_cache: JAX's persistent compilation cache directory, or False.
      memory_fraction: GPU memory JAX preallocates, or None.
    """

    # where JAX caches, how much memory it takes: neither changes the stream, so neither
    # enters the configuration's identity (`simloader.identity.STREAM_UNCHANGED`)
    compilation_cache: Any = dataclasses.field(metadata={"stream": False})
    memory_fraction: Optional[float] = dataclasses.field(metadata={"stream": False})
    # what the checks put on the device, for the constructing process's first program to
    # reuse (not part of what the options are; not sent to workers)
    placed: Optional[Placed] = dataclasses.field(default=None, compare=False, repr=False)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "placed": None}

    def simulated_by(self) -> str:
        return "MJX on JAX"


def check_options(config: SimConfig, options: dict[str, Any], reason: str) -> MjxOptions:
    """Validates the options of MJX on JAX (`backend="mjx"`, chosen for `reason`) and the
    model(s), in the constructing process.

    Args:
      config: the validated dataset configuration.
      options: keyword options of `SimDataset` beyond its own:
        compilation_cache: directory of JAX's persistent compilation cache; None (default):
          JAX's configured one, else `~/.cache/simloader/jax`; False: leave JAX's setting.
        memory_fraction: fraction of GPU memory JAX preallocates; None (default): none, JAX
          allocates as it goes (effective only if JAX has not started yet).
      reason: why MJX simulates (asked, or what `backend="auto"` estimated).

    Returns:
      The options, defaults resolved.

    Raises:
      TypeError: a value of the wrong type.
      ValueError: a bad option value, a model MJX cannot simulate, models or variants that
        differ in what MJX compiles in, a parameter MJX cannot randomize (`randomize.py`),
        cameras (MJX-JAX does not render).
    """
    if config.dtype == torch.float64 and not jax.config.jax_enable_x64:
        # stacklevel: the user's line (here, the entry, binding.bind, SimDataset, the user)
        warnings.warn("dtype=torch.float64 with backend='mjx': MJX simulates in float32 "
                      "(JAX without jax_enable_x64), so the tensors are float32 values "
                      "up-cast to float64", UserWarning, stacklevel=5)
    cache = compilation_cache(options.get("compilation_cache"))
    fraction = memory_fraction(options.get("memory_fraction"))
    runtime.configure_memory(fraction)
    runtime.configure_cache(cache)
    device = runtime.jax_device(config.device)
    images = [o for o in config.observations if isinstance(o, observe.CameraImage)]
    placed = Placed.put(config, device)
    mjx_observe.check(config.observations, placed.data0)
    if images:
        raise ValueError(f"record: backend='mjx' cannot render {[o.key for o in images]}: "
                         f"MJX does not render; use backend='warp' on a CUDA GPU, or "
                         f"backend='cpu'")
    # the batches in flight (prefetched, being simulated, being consumed), float32 outputs
    memory.check_batch_fits(config, runtime.memory_available(device), f"{device.platform} "
                             f"memory", count=config.prefetch + 2, itemsize=4)
    if config.randomization is not None:
        mjx_randomize.check(config.model, placed.model, config.randomization)
    return MjxOptions(cache, fraction, placed)


def memory_fraction(value: Any) -> Optional[float]:
    """The `memory_fraction` option: None (JAX preallocates no GPU memory), or the fraction of
    the GPU it preallocates.

    Raises:
      TypeError, ValueError: `value` is not None or a number in (0, 1].
    """
    if value is not None and (isinstance(value, bool) or not isinstance(
            value, (int, float, np.floating, np.integer))):
        raise TypeError(f"memory_fraction: expected None or a number in (0, 1], got "
                        f"{type(value).__name__} {value!r}")
    if value is not None and not 0 < value <= 1:
        raise ValueError(f"memory_fraction: expected None or a number in (0, 1], got "
                         f"{value}")
    return None if value is None else float(value)


def compilation_cache(value: Any) -> Any:
    """The `compilation_cache` option: the directory of JAX's persistent compilation cache
    (None: JAX's configured one, else `~/.cache/simloader/jax`), or False (JAX's setting left
    alone).

    Raises:
      TypeError: `value` is not a path, None or False.
    """
    if value is False:
        return False
    if value is None:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
        return jax.config.jax_compilation_cache_dir or os.path.join(base, "simloader", "jax")
    if isinstance(value, (str, os.PathLike)):
        return os.fspath(value)
    raise TypeError(f"compilation_cache: expected a directory path, None (default cache) or "
                    f"False (leave JAX's setting), got {type(value).__name__} {value!r}")
