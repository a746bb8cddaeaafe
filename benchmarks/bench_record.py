"""What recording named fields costs: each engine recording `("qpos", "qvel", "xpos")` next to
recording `"state"` alone (issue target: at most 5% of throughput on the GPU engines), and
what `record_kinematics="frame"` adds: the same fields of the frame itself (a position and
velocity pass after every step), and `("xpos", "sensordata", "qacc")` of the frame (a whole
`mj_forward`), in one process, alternately.

    python benchmarks/bench_record.py --quick --backends cpu mjx     # CPU smoke run
    python benchmarks/bench_record.py --backends cpu --workloads humanoid:256x100 --save
    python benchmarks/bench_record.py --save --results-dir $OUT      # on the GPU machine
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

from collections.abc import Callable  # noqa: E402

import common  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("humanoid", 8192, 200)]
QUICK = [common.Workload("cartpole", 32, 10)]
# name -> (record, record_kinematics)
RECORDS = {"state": (("state",), "before_step"),
           "qpos, qvel, xpos": (("qpos", "qvel", "xpos"), "before_step"),
           "qpos, qvel, xpos of the frame": (("qpos", "qvel", "xpos"), "frame"),
           "xpos, sensordata, qacc of the frame": (("xpos", "sensordata", "qacc"), "frame")}


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--backends", nargs="+", default=["mjx", "warp"],
                   choices=("cpu", "mjx", "warp"))
    args = common.parse(p)
    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        for engine in args.backends:
            sims = {name: bench.SimloaderMeasure(model, w, engine, args.seed, record=record,
                                                 record_kinematics=kinematics)
                    for name, (record, kinematics) in RECORDS.items()}
            nbatches = common.batches_for(args, max(s.first_s for s in sims.values()) / 10)
            measures: dict[str, Callable[[], float]] = {
                name: (lambda sim=sim: sim.measure(nbatches)) for name, sim in sims.items()}
            results = common.interleave(measures, args.repeats, desc=f"{w} {engine}")
            for name, s in results.items():
                rows.append([str(w), engine, name, common.ns(s), common.rate(1 / s),
                             f"{results['state'] / s:.3f}"])
    table = common.markdown_table(["workload", "backend", "record", "ns/step", "steps/s",
                                   "throughput / state alone"], rows)
    common.report(args, "bench_record", "Recording named fields, of the step or of the frame",
                  [f"Medians of {args.repeats} alternating repetitions; simloader delivered "
                   f"throughput (torch tensors in hand).", table])


if __name__ == "__main__":
    main()
