"""simloader's CPU backend next to raw `mujoco.rollout` on all cores and a Python `mj_step` loop.

All three do the same work: `nbatch` trajectories of `nstep` steps from the model's default
state, controls drawn uniformly within `ctrlrange` with NumPy for every batch, the
`mjSTATE_FULLPHYSICS` state and the sensors recorded after every step. simloader is timed as
delivered (tensors in hand, a producer thread simulating batch k+1 while batch k is held) over
`--batches` batches (more if they take under `--min-seconds`) after a warm-up batch; raw
rollout as as many back-to-back calls; the Python loop over `--python-steps` steps of one
MjData (extrapolated per step). The three run alternately in one process and the medians of
`--repeats` repetitions are reported.

    python benchmarks/bench_rollout.py --quick
    python benchmarks/bench_rollout.py --save                  # 16-core anchors of performance.md
    python benchmarks/bench_rollout.py --workloads humanoid:4096x200 --repeats 5
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import mujoco
import numpy as np
from mujoco import rollout

import common
import simloader

DEFAULT = [common.Workload("cartpole", 8192, 1000), common.Workload("humanoid", 4096, 200)]
QUICK = [common.Workload("cartpole", 256, 200), common.Workload("humanoid", 64, 50)]
TARGET = 0.95  # simloader / raw rollout throughput (performance.md)

PYTHON, RAW, SIMLOADER = "Python mj_step loop", "mujoco.rollout (raw)", "simloader rollout"


def default_state(model: mujoco.MjModel) -> np.ndarray:
    """The FULLPHYSICS state `mj_resetData` gives (simloader's `initial_state=None`)."""
    data = mujoco.MjData(model)
    state = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    return state


def python_loop(model: mujoco.MjModel, nstep: int, total_steps: int,
                seed: int) -> Callable[[], float]:
    """A measure (seconds per step) of one MjData stepped from Python.

    Trajectories of `nstep` steps, state and sensors recorded after each step into
    preallocated arrays, as the batched methods record them.
    """
    data = mujoco.MjData(model)
    low, high = common.ctrl_bounds(model)
    rng = np.random.default_rng(seed)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.empty((nstep, mujoco.mj_stateSize(model, spec)))
    sensordata = np.empty((nstep, model.nsensordata))
    ntraj = max(1, total_steps // nstep)
    length = min(nstep, total_steps)

    def measure() -> float:
        start = time.perf_counter()
        for _ in range(ntraj):
            mujoco.mj_resetData(model, data)
            control = rng.uniform(low, high, size=(length, model.nu))
            for t in range(length):
                data.ctrl[:] = control[t]
                mujoco.mj_step(model, data)
                mujoco.mj_getState(model, data, state[t], spec)
                sensordata[t] = data.sensordata
        return (time.perf_counter() - start) / (ntraj * length)

    measure()  # warm-up
    return measure


def raw_rollout(model: mujoco.MjModel, w: common.Workload, nthread: int,
                seed: int) -> tuple[Callable[[int], float], float]:
    """A measure (seconds per step) of back-to-back `mujoco.rollout` calls, and the seconds
    of one call.

    One MjData per thread and a persistent thread pool, fresh uniform controls and fresh
    output arrays every call (as simloader allocates a new tensor per batch).
    """
    datas = [mujoco.MjData(model) for _ in range(nthread)]
    x0 = np.tile(default_state(model), (w.nbatch, 1))
    low, high = common.ctrl_bounds(model)
    rng = np.random.default_rng(seed)

    def one_batch():
        control = rng.uniform(low, high, size=(w.nbatch, w.nstep, model.nu))
        return rollout.rollout(model, datas, x0, control, persistent_pool=True)

    def measure(nbatches: int) -> float:
        start = time.perf_counter()
        for _ in range(nbatches):
            state, sensordata = one_batch()
            del state, sensordata
        return (time.perf_counter() - start) / (nbatches * w.steps)

    one_batch()  # warm-up: starts the pool, touches the code paths
    return measure, measure(1) * w.steps


def simloader_rollout(model: mujoco.MjModel, w: common.Workload,
                      seed: int) -> Callable[[int], float]:
    """A measure (seconds per step) of simloader's delivered throughput, backend "rollout"."""
    ds = simloader.SimDataset(model, backend="rollout", nbatch=w.nbatch, nstep=w.nstep,
                              control=simloader.controls.Uniform(), seed=seed)
    return lambda nbatches: common.time_stream(ds, nbatches).steady_s / (nbatches * w.steps)


def cpu_measures(model: mujoco.MjModel, w: common.Workload, args: argparse.Namespace
                 ) -> tuple[dict[str, Callable[[], float]], dict[str, str], int]:
    """The Python loop, raw rollout and simloader rollout measures, where each runs, and the
    timed batches per repetition."""
    raw, batch_s = raw_rollout(model, w, common.cpu_count(), args.seed)
    sim = simloader_rollout(model, w, args.seed)
    nbatches = common.batches_for(args, batch_s)
    measures = {
        PYTHON: python_loop(model, w.nstep, args.python_steps, args.seed),
        RAW: lambda: raw(nbatches),
        SIMLOADER: lambda: sim(nbatches),
    }
    cores = f"{common.cpu_count()} cores"
    return measures, {PYTHON: "1 core", RAW: cores, SIMLOADER: cores}, nbatches


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    args = common.parse(p)

    table, counts = [], []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        measures, runs_on, nbatches = cpu_measures(model, w, args)
        results = common.interleave(measures, args.repeats, desc=str(w))
        table += common.method_rows(w, results, runs_on, {SIMLOADER: RAW}, PYTHON)
        counts.append(f"{nbatches} for {w}")

    text = common.markdown_table(common.HEADERS, table)
    notes = (f"Medians of {args.repeats} alternating repetitions; simloader and raw time as many "
             f"batches each after a warm-up ({', '.join(counts)}); the Python loop "
             f"{args.python_steps} steps. Target: simloader throughput / raw >= {TARGET}. On a "
             f"machine other than the 16-core GPU host only ratios mean something.")
    if args.save:
        common.save(args, "bench_rollout", "simloader rollout backend vs mujoco.rollout",
                    [notes, text])
    print(notes)
    print(text)


if __name__ == "__main__":
    main()
