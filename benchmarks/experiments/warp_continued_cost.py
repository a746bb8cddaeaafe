"""Where a continued Warp stream's time goes: simloader's Warp engine with and without
`continue_episodes=True`, next to raw MuJoCo Warp (one captured step graph, the same work)
whose worlds either continue from batch to batch or are put back at the model's initial state
before every batch, all in one process, alternately (issue 65: a continued stream measured
0.89x the same stream not continued, humanoid 4096 x 100 on an H200).

If raw MuJoCo Warp slows down by the same factor when its worlds continue, the cost is the
physics of the continued worlds (a humanoid under random controls falls and lies on the floor:
more contacts, more constraint rows, more solver work per step), not simloader's bookkeeping;
the contacts per world at the end of a batch are printed beside each.

    python benchmarks/experiments/warp_continued_cost.py --save --results-dir $OUT --tag h200
"""

from __future__ import annotations

import os
import sys
import time

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
import mujoco  # noqa: E402
import torch  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("humanoid", 4096, 100)]
QUICK = [common.Workload("cartpole", 64, 10)]


def reset_each_batch(raw: bench.RawWarp, initial: list[torch.Tensor]) -> None:
    """The raw loop's worlds back at the model's initial state (time, qpos, qvel, act as
    make_data leaves them; warmstart zero), as simloader restarts a stream not continued."""
    for part, value in zip(raw.parts, initial):
        part.copy_(value)
    raw.wp.to_torch(raw.d.qacc_warmstart).zero_()


def contacts(nacon: int, nworld: int) -> str:
    return f"{nacon / nworld:.1f}"


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    args = common.parse(p)
    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        sims = {"simloader, not continued": bench.SimloaderMeasure(model, w, "warp", args.seed),
                "simloader, continue_episodes=True": bench.SimloaderMeasure(
                    model, w, "warp", args.seed, continue_episodes=True)}
        options = sims["simloader, not continued"].ds.config.options
        raws = {"raw MuJoCo Warp, worlds continue": bench.RawWarp.matching(model, w, args.seed,
                                                                          options),
                "raw MuJoCo Warp, worlds reset every batch": bench.RawWarp.matching(
                    model, w, args.seed, options)}
        fresh = raws["raw MuJoCo Warp, worlds reset every batch"]
        # the model's initial state, as mj_resetData leaves it: time 0, qpos0, rest
        data = mujoco.MjData(model)
        initial = [torch.as_tensor(value, dtype=part.dtype, device=part.device).reshape(1, -1)
                   .expand_as(part) for part, value in
                   zip(fresh.parts, (data.time, data.qpos, data.qvel, data.act))]
        nbatches = common.batches_for(args, max(s.first_s for s in sims.values()) / 10)
        nacon: dict[str, list[int]] = {name: [] for name in raws}

        def raw_measure(name: str) -> float:
            raw = raws[name]
            total = 0.0
            for _ in range(nbatches):
                if raw is fresh:  # outside the timed part, as simloader's reset is inside
                    reset_each_batch(raw, initial)
                common.sync()
                start = time.perf_counter()
                raw()
                total += time.perf_counter() - start
            nacon[name].append(int(raw.d.nacon.numpy()[0]))
            return total / (nbatches * w.steps)

        measures = {name: (lambda sim=sim: sim.measure(nbatches)) for name, sim in sims.items()}
        measures.update({name: (lambda name=name: raw_measure(name)) for name in raws})
        results = common.interleave(measures, args.repeats, desc=str(w))
        base = results["simloader, not continued"]
        for name, s in results.items():
            seen = nacon.get(name)
            rows.append([str(w), name, common.ns(s), common.rate(1 / s), f"{base / s:.3f}",
                         "-" if not seen else contacts(seen[-1], w.nbatch)])
    table = common.markdown_table(["workload", "method", "ns/step", "steps/s",
                                   "throughput / simloader not continued",
                                   "contacts per world (last batch)"], rows)
    common.report(args, "warp_continued_cost", "A continued Warp stream: physics or bookkeeping",
                  [f"Medians of {args.repeats} alternating repetitions. The raw loop that resets "
                   "its worlds does so outside its timed part.", table])


if __name__ == "__main__":
    main()
