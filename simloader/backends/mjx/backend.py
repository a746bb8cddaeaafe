"""The MJX backend: a configuration's program on the device, and its hand-off to torch.

`produce` only dispatches (JAX runs asynchronously); `deliver` waits for the results and hands
every output to torch through DLPack: the delivered tensors are the JAX buffers, on the torch
device of the JAX device (`cuda:k` for JAX GPU k). They are fresh buffers for every batch, but
shared with JAX: treat them as read-only (clone before editing in place). In a (spawned)
DataLoader worker, GPU tensors are copied once into torch's memory, the only GPU memory torch
can pass to the main process; `num_workers=0` needs no worker and no copy.

The options and checks at construction are `options.py`'s. Process-wide JAX settings
(`runtime.py`): unless told otherwise, JAX does not preallocate GPU memory (so that a torch
model can train on the same GPU) and compilations are kept in a persistent cache.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import weakref
from collections.abc import Callable
from typing import Any, Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import torch

from simloader import handoff, layout, resume, seeds, sharding
from simloader import randomize as dr
from simloader.backends.base import Backend, Stats
from simloader.backends.mjx import drivers, runtime
from simloader.backends.mjx.options import MjxOptions
from simloader.backends.mjx.program import BatchArgs, Program
from simloader.config import SimConfig


# programs by configuration and device; each epoch's iterator reuses its dataset's program,
# which goes away with the dataset's configuration
_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
# the state rows a continuing trajectory carries: its physics and MuJoCo's warmstart
_WARMSTART = int(mujoco.mjtState.mjSTATE_WARMSTART)
_ROWS = layout.FULLPHYSICS | _WARMSTART


@dataclasses.dataclass
class _Produced:
    outputs: dict[str, Any]  # arrays (and the `params` dict), dispatched, maybe not ready yet
    dispatched: float  # time.perf_counter() at dispatch
    carry: Any = None  # continue_episodes: what the next batch continues from
    extras: Optional[dict[str, torch.Tensor]] = None  # closed loop: the policy's extras


class MjxBackend(Backend):
    """`backend="mjx"`: MJX on JAX.

    Args:
      config, shard, stats: as every backend.
      options: as resolved by `check_options`.

    Raises:
      RuntimeError: in a forked DataLoader worker, where JAX would deadlock.
    """

    def __init__(self, config: SimConfig, shard: sharding.Shard, stats: Stats,
                 options: MjxOptions):
        runtime.refuse_forked_worker()
        super().__init__(config, shard, stats)
        # again here: a spawned worker inherits the environment but not JAX's configuration
        runtime.configure_memory(options.memory_fraction)
        runtime.configure_cache(options.compilation_cache)
        device = runtime.jax_device(config.device)
        self.driver = drivers.driver(config, device, stats)  # the open or the closed loop
        programs = _PROGRAMS.setdefault(config, {})
        self.program = programs.get((device, options))
        if self.program is None:
            placed = options.placed if options.placed and options.placed.device == device \
                else None
            self.program = programs[device, options] = Program(
                config, device, options.compilation_cache, placed)
        self.options = options
        self.device = device
        self.carry: Any = None
        self.restart: Any = None
        if config.continue_episodes:
            # the first batch starts every row from x0, so any carry of the right shapes will do
            self.carry = jax.device_put(self.program.pieces.blank_carry, device)
            self.restart = np.ones(config.nbatch, dtype=bool)
        self.last_ready = 0.0
        self.last_dispatched: Any = None  # outputs of the newest dispatched batch
        self.in_worker = torch.utils.data.get_worker_info() is not None

    def batch_args(self, index: int) -> BatchArgs:
        """The batch function's arguments for batch `index` (`program.batch_function`)."""
        c, p = self.config, self.program
        x0 = p.x0 if p.x0 is not None else c.initial.sample(
            self.seed(index, seeds.INITIAL), c.nbatch).astype(p.dtype)
        randomize_seed = self.seed(index, seeds.RANDOMIZE)
        keys = np.stack([self.seed(index, seeds.CONTROL).generate_state(2, np.uint32),
                         randomize_seed.generate_state(2, np.uint32)])
        variant = None if c.variants is None else dr.draw_variants(
            randomize_seed, len(c.variants), c.nbatch).astype(np.int32)
        fresh = self.fresh_draws(index)
        if fresh is not None:
            fresh = fresh.astype(p.dtype)
        return BatchArgs(p.model, p.data0, p.inputs0, x0, p.control, p.bounds, keys, variant,
                         self.carry, self.restart, fresh, p.reset_control)

    def produce(self, index: int) -> _Produced:
        c = self.config
        dispatched, outputs, carry, extras = self.driver.dispatch(self.program,
                                                                  self.batch_args(index))
        self.last_dispatched = outputs
        if c.continue_episodes:
            # diverged rows restart in the next batch, decided on the device without waiting
            self.carry, self.restart = carry, outputs["diverged"]
        return _Produced(outputs, dispatched, carry, extras)

    def deliver(self, produced: _Produced) -> dict[str, torch.Tensor]:
        c = self.config
        # waiting here also orders the hand-off before any torch stream reads the buffers
        outputs = jax.block_until_ready(produced.outputs)
        ready = time.perf_counter()
        # the device runs batches in order: this one started at its dispatch or when the
        # previous one was ready, whichever is later (when the consumer is slower than the
        # simulation, results wait and this over-counts)
        self.stats.add(simulate_s=ready - max(produced.dispatched, self.last_ready),
                       batches=1, steps=c.nbatch * c.nstep,
                       diverged=int(np.count_nonzero(outputs["diverged"])))
        self.last_ready = ready
        # `dtype=` converts floating outputs; integer and bool records, and images (depth
        # stays float32 metres), keep their dtype
        batch = {key: self._tensor(array, c.dtype if jnp.issubdtype(array.dtype, jnp.floating)
                                   else None)
                 for key, array in outputs.items() if key != "params"}
        batch.update({k: handoff.to_target(v, c.device, None)
                      for k, v in (produced.extras or {}).items()})
        if "params" in outputs:
            # variant indices as the CPU engine gives them (JAX has no int64 without x64)
            batch["params"] = {key: self._tensor(outputs["params"][key],
                                                 torch.int64 if key == "variant" else c.dtype)
                               for key in self.program.param_keys}
        return batch

    def _tensor(self, array: jax.Array, dtype: Optional[torch.dtype]) -> torch.Tensor:
        # the JAX array's memory through DLPack: no copy, same device
        tensor = handoff.to_target(torch.from_dlpack(array), self.config.device, dtype)
        if (self.in_worker and tensor.is_cuda
                and tensor.data_ptr() == array.unsafe_buffer_pointer()):
            # CUDA IPC, which carries a worker's tensors to the main process, shares only
            # torch's own allocations, not JAX's: a worker hands over a copy
            tensor = tensor.clone()
        return tensor

    def checkpoint(self, produced: _Produced) -> Optional[dict[str, Any]]:
        if not self.config.continue_episodes:
            return None
        carry, model = produced.carry, self.config.model
        state = np.asarray(carry["state"])
        rows = np.empty((len(state), mujoco.mj_stateSize(model, _ROWS)), dtype=state.dtype)
        rows[:, layout.component_columns(model, _ROWS, layout.FULLPHYSICS)] = state
        rows[:, layout.component_columns(model, _ROWS, _WARMSTART)] = carry["qacc_warmstart"]
        encoded = resume.encode_trajectories(
            _ROWS, rows, np.asarray(produced.outputs["diverged"]),
            {k: np.asarray(v) for k, v in carry["params"].items()})
        if "pending" in carry:
            encoded["episodes"] = resume.encode_episodes(np.asarray(carry["pending"]),
                                                         np.asarray(carry["episode_steps"]))
        return encoded

    def restore(self, trajectories: dict[str, Any]) -> None:
        rows, self.restart, params = resume.decode_trajectories(trajectories, _ROWS)
        model = self.config.model
        carry = {"state": rows[:, layout.component_columns(model, _ROWS, layout.FULLPHYSICS)],
                 "qacc_warmstart": rows[:, layout.component_columns(model, _ROWS, _WARMSTART)],
                 "params": params}
        if self.config.terminate is not None:
            pending, steps = resume.decode_episodes(trajectories, self.config.nbatch)
            carry.update(pending=pending, episode_steps=steps.astype(np.int32))
        self.carry = jax.device_put(carry, self.device)

    def close(self, _finalizing: Callable[[], bool] = sys.is_finalizing) -> None:
        # (`_finalizing` is bound at definition: at exit this module's globals may be gone)
        # batches already dispatched but never delivered would otherwise keep the GPU busy
        # (and their memory held) after the iterator is gone; the device runs them in order,
        # so waiting for the last one waits for all. Not at interpreter exit (an iterator left
        # open): the process and its device work end anyway, and modules are being torn down
        if self.last_dispatched is not None and not _finalizing():
            jax.block_until_ready(self.last_dispatched)
        # the carry is this iterator's; the program stays for the dataset's next iterator
        self.carry = self.restart = self.last_dispatched = None
