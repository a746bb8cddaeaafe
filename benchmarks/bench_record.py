"""What recording named fields costs: simloader's GPU engines recording `("qpos", "qvel",
"xpos")` next to recording `"state"` alone, on each GPU engine (mjx, warp), in one process,
alternately (issue target: at most 5% of throughput).

    python benchmarks/bench_record.py --quick                        # CPU smoke run
    python benchmarks/bench_record.py --save --results-dir $OUT      # on the GPU machine
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

from collections.abc import Callable  # noqa: E402

import common  # noqa: E402
from simloader.tools import bench  # noqa: E402

DEFAULT = [common.Workload("humanoid", 8192, 200)]
QUICK = [common.Workload("cartpole", 32, 10)]
RECORDS = {"state": ("state",), "qpos, qvel, xpos": ("qpos", "qvel", "xpos")}


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--backends", nargs="+", default=["mjx", "warp"], choices=("mjx", "warp"))
    args = common.parse(p)
    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        for engine in args.backends:
            sims = {name: bench.SimloaderMeasure(model, w, engine, args.seed, record=record)
                    for name, record in RECORDS.items()}
            nbatches = common.batches_for(args, max(s.first_s for s in sims.values()) / 10)
            measures: dict[str, Callable[[], float]] = {
                name: (lambda sim=sim: sim.measure(nbatches)) for name, sim in sims.items()}
            results = common.interleave(measures, args.repeats, desc=f"{w} {engine}")
            for name, s in results.items():
                rows.append([str(w), engine, name, common.ns(s), common.rate(1 / s),
                             f"{results['state'] / s:.3f}"])
    table = common.markdown_table(["workload", "backend", "record", "ns/step", "steps/s",
                                   "throughput / state alone"], rows)
    common.report(args, "bench_record", "Recording named fields on MJX",
                  [f"Medians of {args.repeats} alternating repetitions; simloader delivered "
                   f"throughput (torch tensors in hand).", table])


if __name__ == "__main__":
    main()
