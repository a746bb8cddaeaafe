"""The Warp engine next to raw MuJoCo Warp loops (the public `mujoco-warp` package), one run.

Rows, per workload, all measured in this process with alternating repetitions (medians):

- raw, no controls (the ceiling): one `mjw.step` captured as a CUDA graph, replayed.
- raw, same work (`simloader.bench.RawWarp`, the baseline of `simloader bench` too): the same
  graph, plus what simloader does per step in the plainest torch a user would write: the
  step's controls copied into `d.ctrl` from a (nworld, nstep, nu) tensor drawn on the GPU
  every batch, and the state (time, qpos, qvel, act) and sensors copied into
  (nworld, nstep, ...) frames.
- simloader open loop: `SimDataset(control=controls.Uniform())` iterated (fresh
  controls drawn every batch, divergence checks, clamping, outputs handed over).
- with --policy: simloader with a 2x256 MLP policy in the loop, next to its open loop.
- with --pixels: cart-pole with one 64x64 RGB camera every step against a raw step + render
  graph loop.
- with --jax: the same workload on MJX-JAX through simloader (`auto` picks per model).

Run on the GPU machine from the repository root:
  python benchmarks/bench_warp.py --model-dir .models/dm_control --save --results-dir $OUT
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import mujoco
import torch

import common
from common import markdown_table

import simloader
from simloader import controls
from simloader import bench

WORKLOADS = [common.Workload("humanoid", 8192, 200), common.Workload("humanoid", 32768, 100),
             common.Workload("cartpole", 8192, 1000)]
QUICK = [common.Workload("cartpole", 64, 20)]


# the raw loop (`simloader bench` compares the Warp engine with it too)
RawWarp = bench.RawWarp


class Simloader:
    """simloader's Warp (or JAX) stream: each timed run is a whole epoch of `batches`
    batches (a fresh iterator: the prefetch thread starts with it and ends before the next
    runner is timed, so no runner's work overlaps another's)."""

    def __init__(self, model, nworld: int, nstep: int, batches: int = 1, **kwargs):
        kwargs.setdefault("backend", "warp")
        self.ds = simloader.SimDataset(model, nbatch=nworld, nstep=nstep,
                                       num_batches=batches, **kwargs)
        self.batches = batches
        self()  # the first epoch: build, capture, compile

    def sizes(self) -> tuple:
        o = self.ds.config.options
        return o.naconmax, o.njmax

    def __call__(self) -> None:
        for b in self.ds:
            del b
        torch.cuda.synchronize()


def mlp(model, device) -> torch.nn.Module:
    nobs = model.nq + model.nv + 1 + model.na

    class Policy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.net = torch.nn.Sequential(
                torch.nn.Linear(nobs, 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                torch.nn.ReLU(), torch.nn.Linear(256, model.nu), torch.nn.Tanh())

        def forward(self, obs):
            return self.net(obs["state"])
    return Policy().to(device)


def measure(runners: dict, steps: int, repeats: int) -> dict[str, float]:
    """Median steps/s of each runner, repetitions alternating between them (`steps` per
    batch; a simloader runner's run is `batches` batches)."""
    times: dict[str, list] = {k: [] for k in runners}
    for r in runners.values():
        r()  # warm-up
    for _ in range(repeats):
        for name, r in runners.items():
            start = time.perf_counter()
            r()
            times[name].append((time.perf_counter() - start) / getattr(r, "batches", 1))
    return {k: steps / statistics.median(v) for k, v in times.items()}


def rows_for(w: common.Workload, model, args) -> list[list]:
    steps = w.nbatch * w.nstep
    n = max(3, int(args.seconds * 4e6 / steps))  # batches per timed simloader run
    ours = Simloader(model, w.nbatch, w.nstep, n, control=controls.Uniform(),
                     **sizes(args))
    runners = {
        "raw MuJoCo Warp graph, no controls (ceiling)": RawWarp(
            model, w, args.seed, ours.sizes(), same_work=False),
        "raw MuJoCo Warp graph, same work": RawWarp(model, w, args.seed, ours.sizes()),
        "simloader warp, open loop": ours,
    }
    if args.policy and w.name == "humanoid":
        runners["simloader warp, 2x256 MLP policy"] = Simloader(
            model, w.nbatch, w.nstep, n, policy=mlp(model, "cuda"), **sizes(args))
    rates = measure(runners, steps, args.repeats)
    if args.jax and w.name == "cartpole":
        # in a process of its own: JAX and torch would share one GPU's memory here
        rates["simloader mjx, open loop (own process)"] = jax_rate(model, w, n,
                                                                          args.repeats)
    same = rates["raw MuJoCo Warp graph, same work"]
    return [[str(w), name, f"{rate / 1e6:.2f}M", f"{rate / same:.3f}"]
            for name, rate in rates.items()]


_JAX_CHILD = """
import json, statistics, sys, time
import simloader
from simloader import controls
from simloader import bench
path, nbatch, nstep, n, repeats = sys.argv[1], *map(int, sys.argv[2:])
ds = simloader.SimDataset(path, backend="mjx", nbatch=nbatch, nstep=nstep,
                          control=controls.Uniform(), num_batches=n)
for b in ds:
    pass
times = []
for _ in range(repeats):
    start = time.perf_counter()
    for b in ds:
        pass
    times.append((time.perf_counter() - start) / n)
print(json.dumps(nbatch * nstep / statistics.median(times)))
"""


def jax_rate(model, w: common.Workload, n: int, repeats: int) -> float:
    """simloader's MJX-JAX steps/s on the workload, timed as `Simloader` times, in a child.

    The child gets this very model as an .mjb file: by name it would load simloader's built-in
    model, which is not --model-dir's (the built-in cart-pole keeps its own sensors and
    camera)."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, f"{w.name}.mjb")
        mujoco.mj_saveModel(model, path, None)
        out = subprocess.run([sys.executable, "-c", _JAX_CHILD, path, str(w.nbatch),
                              str(w.nstep), str(n), str(repeats)], capture_output=True,
                             text=True,
                             env={**os.environ, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"})
    if out.returncode:
        raise SystemExit(f"the JAX child failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


_RAW_START = """
import sys, time
import numpy as np, torch, mujoco, warp as wp, mujoco_warp as mjw
wp.config.quiet = True
path, nworld, nstep = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
m = mujoco.MjModel.from_xml_path(path)
with wp.ScopedDevice("cuda:0"):
    wm = mjw.put_model(m); d = mjw.make_data(m, nworld=nworld)
    ctrl = wp.to_torch(d.ctrl)
    u = torch.rand((nworld, nstep, m.nu), device="cuda") * 2 - 1
    mjw.step(wm, d)
    with wp.ScopedCapture() as cap:
        mjw.step(wm, d)
    states = []
    for t in range(nstep):
        ctrl.copy_(u[:, t]); wp.capture_launch(cap.graph)
        states.append(wp.to_torch(d.qpos).clone())
    torch.cuda.synchronize()
"""
_OURS_START = """
import sys
import torch, simloader
name, nworld, nstep = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
ds = simloader.SimDataset(name, backend="warp", nbatch=nworld, nstep=nstep,
                          control=simloader.controls.Uniform(), num_batches=1)
batch = next(iter(ds)); torch.cuda.synchronize()
"""


def startup_rows(args) -> list[list]:
    """First batch of a fresh process (process wall, warm kernel caches): a raw MuJoCo Warp
    script and simloader, alternating."""
    name, nworld, nstep = "humanoid", 8192, 200
    runs = {"raw MuJoCo Warp script": (_RAW_START, str(simloader.builtin_path(name))),
            "simloader warp": (_OURS_START, name)}
    times: dict[str, list] = {k: [] for k in runs}
    for i in range(args.repeats + 1):  # the first round warms the kernel caches
        for label, (script, model) in runs.items():
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", script, model, str(nworld), str(nstep)],
                           check=True, capture_output=True)
            if i:
                times[label].append(time.perf_counter() - start)
    raw = statistics.median(times["raw MuJoCo Warp script"])
    return [[f"{name}:{nworld}x{nstep}", label, f"{statistics.median(t):.2f} s "
             f"({min(t):.2f}-{max(t):.2f})", f"{statistics.median(t) / raw:.3f}"]
            for label, t in times.items()]


def pixel_rows(args) -> list[list]:
    model = simloader.load_model("cartpole")
    nworld, nstep = (64, 10) if args.quick else (16384, 50)
    n = max(3, int(args.seconds * 2e6 / (nworld * nstep)))  # batches per timed epoch
    ours = Simloader(model, nworld, nstep, n,
                     record=("state", simloader.Camera(0, height=64, width=64)))
    runners = {
        "raw MuJoCo Warp step + render graph, RGB copied out": RawWarp(
            model, common.Workload("cartpole", nworld, nstep), args.seed, ours.sizes(),
            same_work=False, cameras=True),
        "simloader warp, Camera 64x64 RGB": ours,
    }
    rates = measure(runners, nworld * nstep, args.repeats)
    raw = rates["raw MuJoCo Warp step + render graph, RGB copied out"]
    return [[f"cartpole:{nworld}x{nstep}", name, f"{rate / 1e6:.2f}M frames/s",
             f"{rate / raw:.3f}"] for name, rate in rates.items()]


def sizes(args) -> dict:
    """MuJoCo Warp's buffer sizes asked on the command line (both loops run with them)."""
    return {k: v for k, v in (("naconmax", args.naconmax), ("njmax", args.njmax)) if v}


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], WORKLOADS, QUICK)
    p.add_argument("--policy", action="store_true", help="add the closed loop (humanoid)")
    p.add_argument("--pixels", action="store_true", help="add the camera workload")
    p.add_argument("--jax", action="store_true", help="add MJX-JAX (cart-pole)")
    p.add_argument("--startup", action="store_true",
                   help="add the first batch of fresh processes (humanoid 8192 x 200)")
    p.add_argument("--naconmax", type=int, help="MuJoCo Warp's contact pool (default: sized)")
    p.add_argument("--njmax", type=int, help="constraint rows per world (default: sized)")
    p.add_argument("--seconds", type=float, default=2.0,
                   help="about how long a timed simloader run lasts")
    args = common.parse(p)
    rows = []
    for w in common.workloads(args, WORKLOADS, QUICK):
        model = (simloader.load_model(w.name) if w.name in ("cartpole", "humanoid")
                 and args.model_dir is None else common.load_model(w.name, args.model_dir))
        rows += rows_for(w, model, args)
        print(markdown_table(["workload", "method", "steps/s", "/ raw same work"], rows),
              flush=True)
    sections = [markdown_table(["workload", "method", "steps/s", "/ raw same work"], rows)]
    if args.pixels:
        sections.append(markdown_table(["workload", "method", "throughput", "/ raw"],
                                       pixel_rows(args)))
    if args.startup:
        sections.append(markdown_table(["workload", "first batch of a fresh process", "wall",
                                        "/ raw"], startup_rows(args)))
    common.report(args, "bench_warp", "The Warp engine against raw MuJoCo Warp", sections)


if __name__ == "__main__":
    main()
