"""Closed loop on the CPU backend: a torch MLP (2 x 256) picks every step's controls from
`(qpos, qvel)`, next to a raw `mujoco.batch` step loop with the same policy and to open-loop
simulation, in one process, alternately, on all cores.

Rows (every one records the state after each step and the controls):
  open loop              simloader, per-step uniform controls (no policy)
  raw Batch.step + torch raw: `mujoco.batch.Batch`, `ctrl[:] = policy(qpos, qvel); step()`
  simloader policy=      simloader, the torch MLP as `policy=` (float32 observations)

    python benchmarks/bench_policy_rollout.py --quick
    python benchmarks/bench_policy_rollout.py --save --results-dir $OUT     # 16-core host
"""

from __future__ import annotations

import closed_loop_baselines as baselines
import common
from simloader import bench

DEFAULT = [common.Workload("cartpole", 4096, 200), common.Workload("humanoid", 1024, 100)]
QUICK = [common.Workload("cartpole", 64, 20)]
RAW = "raw Batch.step + torch"


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--hidden", type=int, default=256, help="units per hidden layer")
    args = common.parse(p)
    import torch

    nthread = common.cpu_count()
    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        net = baselines.mlp(model.nq + model.nv, model.nu, args.hidden, args.seed)
        policy = baselines.StatePolicy(net, model)
        sims = {
            "open loop": bench.SimloaderMeasure(model, w, "cpu", args.seed,
                                                record=("state",), nthread=nthread),
            "simloader policy=": bench.SimloaderMeasure(
                model, w, "cpu", args.seed, control=None, policy=policy,
                record=("state", "qpos", "qvel"), dtype=torch.float32, nthread=nthread),
        }
        raw = baselines.RawClosedLoopBatch(model, w, policy, nthread)
        nbatches = common.batches_for(args, max([s.first_s for s in sims.values()]
                                                + [raw.measure(1) * w.steps]))
        measures = {RAW: lambda: raw.measure(nbatches)}
        measures.update({name: (lambda s=s: s.measure(nbatches)) for name, s in sims.items()})
        results = common.interleave(measures, args.repeats, desc=str(w))
        for name in ("open loop", RAW, "simloader policy="):
            s = results[name]
            rows.append([str(w), name, common.ns(s), common.rate(1 / s),
                         f"{results[RAW] / s:.3f}", f"{results['open loop'] / s:.3f}"])
    table = common.markdown_table(["workload", "what", "ns/step", "steps/s", "vs raw loop",
                                   "vs open loop"], rows)
    common.report(args, "bench_policy_rollout", "Closed loop on the CPU: a torch MLP per step",
                  [f"Medians of {args.repeats} alternating repetitions on {nthread} threads; "
                   f"delivered throughput (tensors in hand, state and controls of every step). "
                   f"Policy: MLP {args.hidden}x{args.hidden} (tanh) of (qpos, qvel), float32 "
                   f"torch on the CPU with {torch.get_num_threads()} intra-op threads.", table])


if __name__ == "__main__":
    main()
