"""The closed-loop driver on MJX: a torch policy picks every step's controls.

A batch is `start` (reset, the initial observations), then `nstep` calls of `advance` (the
policy's rows applied, one step, the next observations), then `finish`, each a jitted function
of the pieces the open loop uses (`program.Pieces`), so both drivers simulate alike. Between
calls, the observations reach torch and the controls come back through DLPack, which orders
the two on the device (the consumer's stream waits on an event of the producer's): nothing
waits on the host, so Python runs ahead of the GPU and the policy and steps queue up back to
back.

The loop's buffers (the batch of `mjx.Data`, the frames recorded so far, the applied
controls) are donated to every call: each step writes them in place, at the same addresses,
instead of allocating a new batch of them per step. The data's buffers are donated on from
batch to batch as well.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import torch

from simloader import controls, rules
from simloader.backends.mjx import observe as mjx_observe
from simloader.backends.mjx.program import seed_key
from simloader.backends.mjx.runtime import mjx


def functions(P: Any, noise_drivers: tuple) -> tuple[Callable, Callable, Callable]:
    """The pure `start`, `advance` and `finish` of a closed-loop batch (`P`: `Pieces`).

    With a callable `terminate=`, `advance` and `finish` take `external`, (nbatch,) uint8:
    the callable's verdict on the observations the previous `advance` returned (where that
    step ended a frame; zeros otherwise). It ends those rows' episodes at that frame, as a
    rule would have (`terminated`, and the autoreset at the next frame)."""
    every, nframes, E = P.every, P.nframes, P.episodes
    checks = E is not None and E.check is not None

    def apply_external(loop, external):
        """The callable's verdict on the frame the last step ended (step `t - 1`)."""
        e, t = loop["episode"], loop["t"]
        last = jnp.maximum(t - 1, 0)
        hit = (external != 0) & (t > 0) & rules.frame_due(last, every)
        j = rules.frame_index(last, every)
        old = jax.lax.dynamic_index_in_dim(e["flags"], j, axis=1, keepdims=False)
        flags = jax.lax.dynamic_update_index_in_dim(
            e["flags"], old | hit.astype(jnp.uint8), j, axis=1)  # bit 1: terminated
        return {**loop, "episode": {**e, "flags": flags, "pending": e["pending"] | hit}}

    def start(m, d0, inputs0, x0, defaults, bounds, seeds, variant, carry, restart, fresh,
              reset_control, previous):
        """The batch's models and reset trajectories, the loop state, and the observations of
        the initial state (derived fields by a forward pass, as `mj_forward` computes them).
        With `terminate`, the loop also holds the episodes' state (`fresh`, `reset_control`:
        as the open loop's batch function takes them).

        `previous`: the last batch's data, donated so the new one takes its buffers."""
        del previous
        m, data, defaults, variant, params = P.begin(m, d0, inputs0, x0, defaults, seeds,
                                                     variant, carry, restart)
        initial = P.physics(m, data)
        low, high = P.bounds(m, bounds, variant)
        shape = P.shape
        noise = (controls.sample_jax(noise_drivers, jnp.zeros(shape[::2], P.dtype),
                                     seed_key(seeds[0]), shape, P.dtype)
                 if noise_drivers else None)
        data = jax.vmap(mjx.forward, (P.model_axes, 0))(m, data)
        obs = mjx_observe.frame(P.observations, P.model_axes, m, data)
        loop = {"d": data, "t": jnp.zeros((), jnp.int32),
                "diverged": jnp.zeros(P.nbatch, bool),
                "frames": {k: jnp.zeros((P.nbatch, nframes, *v.shape[1:]), v.dtype)
                           for k, v in obs.items()},
                "control": jnp.zeros(shape, P.dtype),
                "low": jnp.broadcast_to(low, shape[::2]).astype(P.dtype),
                "high": jnp.broadcast_to(high, shape[::2]).astype(P.dtype)}
        if noise is not None:
            loop["noise"] = noise
        if E is not None:
            source, reset_control = P.episode_inputs(x0, reset_control, variant)
            n = P.nbatch
            pending = (carry["pending"] & ~restart if P.continuing else jnp.zeros(n, bool))
            loop["episode"] = {
                "pending": pending, "held": jnp.zeros(n, bool),
                "steps": (jnp.where(restart, 0, carry["episode_steps"]) if P.continuing
                          else jnp.zeros(n, jnp.int32)),
                "resets": jnp.zeros(n, jnp.int32),
                "at": jnp.zeros_like(initial), "source": source, "fresh": fresh,
                "reset_control": jnp.broadcast_to(reset_control, shape[::2]).astype(P.dtype),
                "flags": jnp.zeros((n, nframes), jnp.uint8)}
        return m, loop, obs, {"initial_state": initial, "params": params}

    def begin_frame(loop, t):
        """At a frame's first step: rows whose last frame met a rule take their next fresh
        state and are held there this frame (as on the CPU engine: the policy saw the ending
        state first). Returns (loop's episode state, data)."""
        e, d = loop["episode"], loop["d"]
        boundary = t % every == 0
        take = boundary & e["pending"]
        at = jnp.where(take[:, None], P.fresh_state(e["source"], e["fresh"], e["resets"]),
                       e["at"])
        e = {**e, "at": at, "resets": e["resets"] + take,
             "held": jnp.where(boundary, e["pending"], e["held"])}
        return e, P.hold(d, take, at)

    def advance(m, loop, u, external=None):
        """One step of every trajectory with the policy's rows `u` (nbatch, ncontrol): the
        loop state after it, and the observations the policy sees next."""
        if checks:
            loop = apply_external(loop, external)
        t = loop["t"]
        u = u.astype(P.dtype)
        if "noise" in loop:
            u = u + jax.lax.dynamic_index_in_dim(loop["noise"], t, axis=1, keepdims=False)
        # as the open loop: a bad row flags its trajectory, MuJoCo's clamp is applied
        u, bad = controls.as_applied(u, loop["low"], loop["high"], jnp)
        d = loop["d"]
        if E is not None:  # a fresh frame's inputs are mj_resetData's
            e, d = begin_frame(loop, t)
            u_step = jnp.where(e["held"][:, None], e["reset_control"], u)
        else:
            u_step = u
        d = jax.vmap(P.step, (P.model_axes, 0, 0))(m, d, u_step)
        d, unstable = P.restart_unstable(m, d)
        if E is not None:  # held at the fresh state, derived fields the step's there
            d = P.hold(d, e["held"], e["at"])
        obs = mjx_observe.frame(P.observations, P.model_axes, m, d, P.frame_stage)
        diverged = loop["diverged"] | unstable | bad
        finite = P.finite(obs)
        if finite is not None:
            diverged = diverged | ~finite
        # frame j holds the values after step (j + 1) * every: written in place when due
        j, due = rules.frame_index(t, every), rules.frame_due(t, every)
        frames = {}
        for key, buffer in loop["frames"].items():
            old = jax.lax.dynamic_index_in_dim(buffer, j, axis=1, keepdims=False)
            frames[key] = jax.lax.dynamic_update_index_in_dim(
                buffer, jnp.where(due, obs[key], old), j, axis=1)
        control = jax.lax.dynamic_update_index_in_dim(loop["control"], u, t, axis=1)
        loop = {**loop, "d": d, "t": t + 1, "diverged": diverged, "frames": frames,
                "control": control}
        if E is not None:  # the frame's flags; at its end, which rows met a rule
            steps = jnp.where(e["held"], 0, e["steps"] + 1)
            no = jnp.zeros(P.nbatch, bool)
            terminated = E.terminated(jnp, P.kinematics(m, d), no)
            truncated = E.truncated(jnp, steps, no)
            flags = jax.lax.dynamic_update_index_in_dim(
                e["flags"], P.pack_flags(terminated, truncated, e["held"]), j, axis=1)
            pending = jnp.where(rules.frame_due(t, every), terminated | truncated, e["pending"])
            loop["episode"] = {**e, "steps": steps, "flags": flags, "pending": pending}
        return loop, obs

    def finish(m, loop, delivered, external=None):
        """The batch's outputs (frames, control, diverged, the initial state and parameters)
        and the carry of `continue_episodes`, from the loop state; and the final data (whose
        buffers the next batch's `start` takes)."""
        if checks:  # the callable's verdict on the last frame
            loop = apply_external(loop, external)
        d, params = loop["d"], delivered["params"]
        outputs = {**loop["frames"], "control": loop["control"], "diverged": loop["diverged"],
                   "initial_state": delivered["initial_state"]}
        if params:
            outputs["params"] = params
        carry = ({"state": P.physics(m, d), "qacc_warmstart": d.qacc_warmstart,
                  "params": params} if P.continuing else None)  # as the open loop's
        if E is not None:
            e = loop["episode"]
            flags, outputs["control"] = P.unpack_flags(e["flags"], outputs["control"])
            outputs.update(flags)
            if carry is not None:
                carry.update(pending=e["pending"], episode_steps=e["steps"])
        return outputs, carry, d

    return start, advance, finish


class ClosedLoop:
    """A configuration's closed-loop batch, compiled on first use; one per program."""

    def __init__(self, pieces: Any, noise_drivers: tuple):
        start, advance, finish = functions(pieces, noise_drivers)
        self.noisy = bool(noise_drivers)  # whether `start` draws noise around the policy
        # donated: the previous data to `start`, the loop state to `advance` and `finish`
        self.start = jax.jit(start, donate_argnums=(10,))
        self.advance = advance
        self.finish = jax.jit(finish, donate_argnums=(1,))
        self.flat: Any = None  # (model and loop tree structures, jitted flat `advance`)
        # data of the batch's structure for the first batch's `start` to take: reset rows, as
        # `start` makes them
        self.blank = jax.jit(lambda *args: pieces.begin(*args)[1])
        # a callable terminate=: run on the observations after every frame, here in Python
        E = pieces.episodes
        self.check = E if E is not None and E.check is not None else None
        self.every, self.nbatch = pieces.every, pieces.nbatch

    def run(self, args: Any, previous: Any, drive: Callable[[dict, Callable], Any]
            ) -> tuple[dict[str, Any], Any, Any, Any]:
        """One batch, its steps driven by `drive(first, step)` (`policy_loop.run` with the
        batch's weights): `first` the observations of the initial state, `step(rows, t)` one
        step of every trajectory with the policy's rows, returning the next observations
        (torch tensors in and out, exchanged with JAX through DLPack). Only dispatches:
        nothing here waits for the device.

        Args:
          args: the open loop's batch function's arguments (`program.BatchArgs`).
          previous: the data the last batch of this iterator returned (donated), or None.
          drive: runs the steps; what it returns is returned last.

        Returns:
          (outputs, carry) as the open loop's, the data for the next batch's `previous`, and
          what `drive` returned.
        """
        # true float32 dot products, as the open loop (JAX's GPU default is TF32)
        with jax.default_matmul_precision("float32"):
            if previous is None:
                a = args
                previous = self.blank(a.model, a.data0, a.inputs0, a.x0, a.control, a.seeds,
                                      a.variant, a.carry, a.restart)
            m, loop, obs, delivered = self.start(*args, previous)
            m_leaves, m_def = jax.tree.flatten(m)
            leaves, loop_def = jax.tree.flatten(loop)
            advance = self._flat_advance(m_def, loop_def)

            first = {k: torch.from_dlpack(v) for k, v in obs.items()}
            none = verdict = (None if self.check is None else jax.dlpack.from_dlpack(
                torch.zeros(self.nbatch, dtype=torch.uint8,
                            device=next(iter(first.values())).device)))

            def step(rows: torch.Tensor, t: int) -> dict[str, torch.Tensor]:
                nonlocal leaves, verdict
                u = jax.dlpack.from_dlpack(rows.contiguous())
                if self.check is None:
                    leaves, obs = advance(m_leaves, leaves, u)
                else:
                    leaves, obs = advance(m_leaves, leaves, u, verdict)
                out = {k: torch.from_dlpack(v) for k, v in obs.items()}
                if self.check is not None:  # after a frame: the callable's verdict
                    verdict = none
                    if (t + 1) % self.every == 0:
                        frame = (t + 1) // self.every - 1
                        ended = self.check.checked(out, frame, self.nbatch)
                        verdict = jax.dlpack.from_dlpack(ended.to(torch.uint8).contiguous())
                return out

            driven = drive(first, step)
            loop = jax.tree.unflatten(loop_def, leaves)
            if self.check is None:
                return (*self.finish(m, loop, delivered), driven)
            return (*self.finish(m, loop, delivered, verdict), driven)

    def _flat_advance(self, m_def: Any, loop_def: Any) -> Callable:
        """`advance` jitted on lists of leaves, the loop's donated. MJX's Model and Data are
        dataclasses that JAX flattens in Python: about 0.8 ms per call on the cart-pole (on
        the CPU box), every step of a closed loop; lists of arrays flatten in C++. Made on
        the first batch, for the structures every batch of the configuration has."""
        if self.flat is None or self.flat[0] != (m_def, loop_def):
            advance = self.advance

            def flat(m_leaves, leaves, u, external=None):
                loop, obs = advance(jax.tree.unflatten(m_def, m_leaves),
                                    jax.tree.unflatten(loop_def, leaves), u, external)
                return jax.tree.leaves(loop), obs

            self.flat = ((m_def, loop_def), jax.jit(flat, donate_argnums=(1,)))
        return self.flat[1]
