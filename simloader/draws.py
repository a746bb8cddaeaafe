"""Random draws and the few array operations the value kinds need, once per array library.

A control generator or a parameter distribution is written once, over a `Draws`: NumPy on the
host (the CPU engine), JAX inside the jitted batch function (MJX), torch on the device (MuJoCo
Warp). Each `Draws` owns its library's random state: a NumPy `Generator`, a JAX key split
into one key per draw, a torch `Generator`. The operations keep each library's own arithmetic
(a NumPy loop where JAX scans), so that every engine's stream is what it was before the value
kinds were written once: same seed, same bits.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class NumpyDraws:
    """NumPy, float64, with `rng` (`np.random.Generator`)."""

    xp = np

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def uniform(self, low: Any, high: Any, shape: tuple[int, ...], like: Any = None) -> Any:
        """Uniform in `[low, high)` (broadcasting to `shape`), in `like`'s dtype (default:
        `low`'s)."""
        return self.rng.uniform(low, high, size=shape)

    def normal(self, shape: tuple[int, ...], like: Any) -> Any:
        """Standard normal draws of `shape` in `like`'s dtype."""
        return self.rng.standard_normal(size=shape)

    def scalar(self, value: Any) -> Any:
        """A one-value parameter as this library computes with it (a Python float on the
        host and in torch; a traced array in JAX)."""
        return float(value)

    def sqrt(self, value: Any) -> Any:
        return np.sqrt(value)

    def clip(self, x: Any, low: Any, high: Any) -> Any:
        return np.clip(x, low, high)

    def broadcast(self, x: Any, shape: tuple[int, ...]) -> Any:
        return np.broadcast_to(x, shape)

    def repeat(self, x: Any, n: int, axis: int) -> Any:
        return np.repeat(x, n, axis=axis)

    def arange(self, n: int, like: Any) -> Any:
        return np.arange(n, dtype=like.dtype)

    def concat_time(self, first: Any, rest: Any) -> Any:
        """`first` (n, k) and `rest` (n, t - 1, k) as one (n, t, k) array."""
        return np.concatenate([first[:, None], rest], axis=1)

    def linear_recurrence(self, x: Any, a: Any) -> Any:
        """`x[:, t] += a * x[:, t - 1]` for t = 1, 2, ... in order (x: (n, t, k), a copy)."""
        out = np.array(x)
        for t in range(1, out.shape[1]):  # vectorized over the batch
            out[:, t] += a * out[:, t - 1]
        return out


class TorchDraws(NumpyDraws):
    """torch, with `generator` (`torch.Generator`), on the device and in the dtype of the
    parameters it is given (the Warp engine draws on the GPU)."""

    def __init__(self, generator: Any):
        import torch
        self.xp = torch
        self.generator = generator

    def _tensor(self, value: Any, like: Any) -> Any:
        return self.xp.as_tensor(value, dtype=like.dtype, device=like.device)

    def uniform(self, low, high, shape, like=None):
        like = low if like is None else like
        low, high = self._tensor(low, like), self._tensor(high, like)
        out = self.xp.rand(shape, generator=self.generator, dtype=like.dtype,
                           device=like.device)
        return out.mul_(high - low).add_(low)

    def normal(self, shape, like):
        return self.xp.randn(shape, generator=self.generator, dtype=like.dtype,
                             device=like.device)

    def sqrt(self, value):
        return value ** 0.5 if isinstance(value, float) else self.xp.sqrt(value)

    def clip(self, x, low, high):
        return self.xp.clamp(x, low, high)

    def broadcast(self, x, shape):
        return x.expand(shape)

    def repeat(self, x, n, axis):
        return x.repeat_interleave(n, dim=axis)

    def arange(self, n, like):
        return self.xp.arange(n, dtype=like.dtype, device=like.device)

    def concat_time(self, first, rest):
        return self.xp.cat([first[:, None], rest], dim=1)

    def linear_recurrence(self, x, a):
        out = x.clone()
        for t in range(1, out.shape[1]):  # vectorized over the batch
            out[:, t].add_(out[:, t - 1], alpha=a)
        return out


class JaxDraws(NumpyDraws):
    """JAX (inside a jitted function), with `key` split into `count` keys, one per draw (a
    single draw takes `key` itself)."""

    def __init__(self, key: Any, count: int = 1):
        import jax
        import jax.numpy as jnp
        self.jax, self.xp = jax, jnp
        self.keys = [key] if count == 1 else list(jax.random.split(key, count))

    def _key(self) -> Any:
        return self.keys.pop(0)

    def uniform(self, low, high, shape, like=None):
        like = low if like is None else like
        return self.jax.random.uniform(self._key(), shape, like.dtype, low, high)

    def normal(self, shape, like):
        return self.jax.random.normal(self._key(), shape, like.dtype)

    def scalar(self, value):
        return value

    def sqrt(self, value):
        return self.xp.sqrt(value)

    def clip(self, x, low, high):
        return self.xp.clip(x, low, high)

    def broadcast(self, x, shape):
        return self.xp.broadcast_to(x, shape)

    def repeat(self, x, n, axis):
        return self.xp.repeat(x, n, axis=axis)

    def arange(self, n, like):
        return self.xp.arange(n, dtype=like.dtype)

    def concat_time(self, first, rest):
        return self.xp.concatenate([first[:, None], rest], axis=1)

    def linear_recurrence(self, x, a):
        """The recurrence as a scan over time (unrolling it would trace nstep steps)."""
        jnp = self.xp

        def step(previous, increment):
            now = a * previous + increment
            return now, now

        _, rest = self.jax.lax.scan(step, x[:, 0], jnp.swapaxes(x[:, 1:], 0, 1))
        return jnp.concatenate([x[:, :1], jnp.swapaxes(rest, 0, 1)], axis=1)
