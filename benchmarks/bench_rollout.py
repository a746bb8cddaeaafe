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
from collections.abc import Callable

import mujoco

import common
import simloader
from simloader import bench

DEFAULT = [common.Workload("cartpole", 8192, 1000), common.Workload("humanoid", 4096, 200)]
QUICK = [common.Workload("cartpole", 256, 200), common.Workload("humanoid", 64, 50)]
TARGET = 0.95  # simloader / raw rollout throughput (performance.md)

PYTHON, RAW, SIMLOADER = bench.PYTHON, bench.RAW_ROLLOUT, bench.SIMLOADER_ROLLOUT
# the baselines are the package's (they back `simloader bench` too)
python_loop, raw_rollout = bench.python_loop, bench.raw_rollout


def simloader_rollout(model: mujoco.MjModel, w: common.Workload,
                      seed: int) -> Callable[[int], float]:
    """A measure (seconds per step) of simloader's delivered throughput, backend "cpu"."""
    # all the cores, as the raw rollout: nothing trains beside this measurement
    ds = simloader.SimDataset(model, backend="cpu", nbatch=w.nbatch, nstep=w.nstep,
                              control=simloader.controls.Uniform(), seed=seed,
                              nthread=common.cpu_count())
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
    common.report(args, "bench_rollout", "simloader rollout backend vs mujoco.rollout",
                  [notes, text])


if __name__ == "__main__":
    main()
