"""Raw closed-loop baselines (a torch policy choosing every step's controls), for
`bench_policy_rollout.py` and `bench_policy_mjx.py`: the benchmark policy, and the raw loops
simloader's `policy=` is measured against (MuJoCo's batch on CPU threads, MJX steps with torch
between them, MuJoCo Warp's captured graph). They live beside the benchmarks, not in the
package: `simloader bench` needs none of them.
"""

from __future__ import annotations

import time
from typing import Any, Optional

import mujoco
import numpy as np

import torch

from simloader.bench import STEP_READS, RawBaseline, Workload
# the benchmark policy, shared with the suite's policy workload (bench_policy_*.py use it
# as closed_loop_baselines.mlp and .StatePolicy)
from simloader.bench.raw import StatePolicy, mlp  # noqa: F401


class RawClosedLoopBatch(RawBaseline):
    """Raw CPU closed loop: `mujoco.batch.Batch` on all cores as its docstring writes it
    (`ctrl[:] = policy(qpos, qvel); batch.step()`), the torch policy on float32 copies of the
    bound state, recording the state after every step and the controls. No clamping, noise,
    divergence checks or hand-off: the floor simloader's `policy=` is measured against.

    Args:
      policy: `StatePolicy` (a CPU torch MLP).
      nthread: the batch's threads.
    """

    def __init__(self, model: mujoco.MjModel, w: Workload, policy: Any, nthread: int):
        import torch
        from mujoco import batch as mj_batch
        self.w, self.policy, self.torch = w, policy, torch
        self.batch = mj_batch.Batch(model, nsim=w.nbatch, nthread=nthread)
        self.fields = {name: self.batch.bind(name)
                       for name in ("time", "qpos", "qvel", "act", "ctrl")}
        self.start = self.batch.state.copy()
        self.nstate = 1 + model.nq + model.nv + model.na

    def __call__(self) -> dict[str, np.ndarray]:
        torch, w, f = self.torch, self.w, self.fields
        self.batch.state[:] = self.start
        state = np.empty((w.nbatch, w.nstep, self.nstate))
        control = np.empty((w.nbatch, w.nstep, f["ctrl"].shape[1]))
        with torch.no_grad():
            for t in range(w.nstep):
                u = self.policy({"qpos": torch.from_numpy(f["qpos"]).float(),
                                 "qvel": torch.from_numpy(f["qvel"]).float()})
                f["ctrl"][:] = u.numpy()
                control[:, t] = f["ctrl"]
                self.batch.step()
                state[:, t] = np.concatenate(
                    [f["time"][:, None], f["qpos"], f["qvel"], f["act"]], axis=1)
        return {"state": state, "control": control}


class RawClosedLoopMjx(RawBaseline):
    """Raw MJX closed-loop baselines, recording the state after every step and the controls.

    mode "fused": the policy's MLP written in JAX, inside one jitted scan (the upper bound: no
      torch, no call per step); "torch": the torch MLP called between jitted single steps,
      JAX<->torch through DLPack both ways, the data and the output buffers donated so that
      they keep their addresses (and MuJoCo Warp its CUDA graph).

    Args:
      net: the torch MLP (`mlp`), on the GPU JAX runs on.
      impl: MJX's implementation, "jax" or "warp" (MJX's vendored MuJoCo Warp through JAX:
        the closed loop simloader ran before its own Warp engine, kept for those figures);
        naconmax, njmax: Warp's contact pool and constraint rows (None: sized by MJX).
    """

    def __init__(self, model: mujoco.MjModel, w: Workload, net: Any, mode: str,
                 impl: str = "jax", naconmax: Optional[int] = None,
                 njmax: Optional[int] = None):
        import jax
        import jax.numpy as jnp
        import torch
        from simloader.backends.mjx.runtime import mjx

        self.w, self.mode, self.net = w, mode, net
        self.policy = StatePolicy(net, model)
        mx = mjx.put_model(model, impl=impl)
        if impl == "warp":
            mx = mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=0)))
        self.mx = mx
        nbatch, nstep = w.nbatch, w.nstep
        if impl == "warp":
            d0 = jax.jit(jax.vmap(lambda _: mjx.make_data(
                model, impl="warp", naconmax=naconmax, njmax=njmax)))(jnp.arange(nbatch))
        else:
            d0 = jax.tree.map(lambda x: jnp.broadcast_to(x, (nbatch, *x.shape)),
                              mjx.make_data(mx, impl="jax"))
        self.d0 = d0
        weights = [jnp.asarray(p.detach().cpu().numpy()) for p in net.parameters()]
        mid, half = (jnp.asarray(x.cpu().numpy()) for x in (self.policy.mid, self.policy.half))
        step = jax.vmap(mjx.step, in_axes=(None, 0))

        def fresh(d):
            # Warp: every input a step reads in a buffer of its own (Warp keys its captured
            # graph on buffer addresses; a scanned input would be re-captured every step)
            if impl != "warp":
                return d
            return d.replace(**{n: getattr(d, n) + 0 * getattr(d, n) for n in STEP_READS})

        def advance(mx, d, u):
            d = fresh(d)
            d = d.replace(ctrl=u + 0 * d.ctrl if impl == "warp" else u)
            d = step(mx, d)
            state = jnp.concatenate([d.time[:, None], d.qpos, d.qvel, d.act], axis=1)
            return d, state

        def jax_mlp(x):
            for i in range(0, len(weights), 2):
                x = jnp.tanh(x @ weights[i].T + weights[i + 1])
            return mid + half * x

        def fused(mx, d):
            def body(d, _):
                u = jax_mlp(jnp.concatenate([d.qpos, d.qvel], axis=1))
                d, state = advance(mx, d, u)
                return d, (state, u)
            _, (states, us) = jax.lax.scan(body, d, None, length=nstep)
            return {"state": states.swapaxes(0, 1), "control": us.swapaxes(0, 1)}

        def one(mx, d, u, out, t):
            d, state = advance(mx, d, u)
            out = {"state": jax.lax.dynamic_update_index_in_dim(out["state"], state, t, 1),
                   "control": jax.lax.dynamic_update_index_in_dim(out["control"], u, t, 1)}
            return d, out, jnp.concatenate([d.qpos, d.qvel], axis=1), t + 1

        start = time.perf_counter()
        with jax.default_matmul_precision("float32"):
            if mode == "fused":
                self.fn = jax.jit(fused).lower(mx, d0).compile()
            else:
                self.one = jax.jit(one, donate_argnums=(1, 3))
        self.compile_s = time.perf_counter() - start
        self.nstate = int(1 + model.nq + model.nv + model.na)
        self.torch = torch
        self.data: Any = None
        start = time.perf_counter()
        self()
        self.first_s = self.compile_s + time.perf_counter() - start

    def __call__(self) -> dict[str, Any]:
        import jax
        import jax.numpy as jnp
        w = self.w
        if self.mode == "fused":
            return jax.block_until_ready(self.fn(self.mx, self.d0))
        d = self.data if self.data is not None else jax.tree.map(
            lambda x: jnp.array(x, copy=True), self.d0)
        out = {"state": jnp.zeros((w.nbatch, w.nstep, self.nstate), jnp.float32),
               "control": jnp.zeros((w.nbatch, w.nstep, len(self.policy.mid)), jnp.float32)}
        obs, t = jnp.concatenate([d.qpos, d.qvel], axis=1), jnp.zeros((), jnp.int32)
        with jax.default_matmul_precision("float32"), self.torch.no_grad():
            for _ in range(w.nstep):
                x = self.torch.from_dlpack(obs)
                u = self.policy({"qpos": x[:, :self.d0.qpos.shape[1]],
                                 "qvel": x[:, self.d0.qpos.shape[1]:]})
                d, out, obs, t = self.one(self.mx, d, jax.dlpack.from_dlpack(u.contiguous()),
                                          out, t)
        self.data = d  # donated on to the next batch: the same buffers, the same graph
        return jax.block_until_ready(out)

class RawWarpGraphLoop(RawBaseline):
    """Raw closed loop on MuJoCo Warp itself, without MJX or simloader: MuJoCo Warp's step
    captured once as a CUDA graph on its own arrays and replayed every step on torch's
    stream, the torch MLP between replays on zero-copy views, recording the state after every
    step and the controls (the scheme simloader's Warp closed loop uses, with nothing else:
    no checks, no noise, no resets beyond the batch's start). GPU only.

    Args:
      net: the torch MLP (`mlp`), on the GPU.
      naconmax, njmax: MuJoCo Warp's buffer sizes, as simloader sizes them.
    """

    def __init__(self, model: mujoco.MjModel, w: Workload, net: Any,
                 naconmax: Optional[int] = None, njmax: Optional[int] = None):
        import torch
        import warp as wp
        import mujoco_warp as mjw  # the package the Warp engine runs

        self.w, self.torch, self.wp = w, torch, wp
        self.policy = StatePolicy(net, model)
        start = time.perf_counter()
        self.wm = mjw.put_model(model)
        self.wm.opt.warn_overflow = 0
        self.wd = mjw.make_data(model, nworld=w.nbatch, naconmax=naconmax, njmax=njmax)
        stream = wp.Stream(wp.get_device())
        with wp.ScopedStream(stream):
            mjw.step(self.wm, self.wd)  # loads the kernels before the capture
            with wp.ScopedCapture(stream=stream) as capture:
                mjw.step(self.wm, self.wd)
        wp.synchronize_stream(stream)
        self.graph = capture.graph
        view = lambda name: wp.to_torch(getattr(self.wd, name))  # noqa: E731
        self.time, self.qpos, self.qvel, self.act, self.ctrl, self.warmstart = (
            view(n) for n in ("time", "qpos", "qvel", "act", "ctrl", "qacc_warmstart"))
        self.reset = {name: view(name).clone() for name in STEP_READS}
        self.nq = model.nq
        self.compile_s = time.perf_counter() - start
        self()
        self.first_s = time.perf_counter() - start

    def __call__(self) -> dict[str, Any]:
        torch, w = self.torch, self.w
        for name, value in self.reset.items():
            getattr(self, "warmstart" if name == "qacc_warmstart" else name).copy_(value)
        state = torch.empty((w.nbatch, w.nstep, 1 + self.qpos.shape[1] + self.qvel.shape[1]
                             + self.act.shape[1]), device=self.qpos.device)
        control = torch.empty((w.nbatch, w.nstep, self.ctrl.shape[1]), device=self.qpos.device)
        stream = self.wp.stream_from_torch(torch.cuda.current_stream())
        with torch.no_grad():
            for t in range(w.nstep):
                u = self.policy({"qpos": self.qpos, "qvel": self.qvel})
                self.ctrl.copy_(u)
                control[:, t] = u
                self.wp.capture_launch(self.graph, stream=stream)
                state[:, t] = torch.cat([self.time[:, None], self.qpos, self.qvel, self.act],
                                        dim=1)
        torch.cuda.current_stream().synchronize()
        return {"state": state, "control": control}


