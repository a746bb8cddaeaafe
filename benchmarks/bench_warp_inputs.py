"""MuJoCo Warp (`impl="warp"`): what each per-step input costs, and the raw recipes around it.

MJX runs Warp's kernels as a CUDA graph keyed on the addresses of its input buffers: an input
that moves from step to step (a slice of the scanned control array) has the graph captured
again every step. simloader gives every input it sets a buffer of its own (`warp_impl.py`).
This script times, in one process and alternately, simloader with each kind of per-step input
(actuator controls, applied generalized forces, Cartesian forces on a body, randomized model
parameters) next to raw `scan(vmap(mjx.step))` recipes: inputs refreshed (`u + 0 * old`), not
refreshed (the trap), and the raw recipe with simloader's per-step divergence check (which
also gives the carried state buffers of their own). A regression in simloader's handling of an
input shows as its row falling towards the "not refreshed" one.

    python benchmarks/bench_warp_inputs.py --quick                 # CPU smoke run (Warp on CPU)
    python benchmarks/bench_warp_inputs.py --save --results-dir $OUT   # on the GPU machine
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

from collections.abc import Callable  # noqa: E402

import mujoco  # noqa: E402

import common  # noqa: E402
from simloader import bench, controls  # noqa: E402
from simloader import randomize as dr  # noqa: E402

S = mujoco.mjtState
DEFAULT = [common.Workload("humanoid", 8192, 200)]
QUICK = [common.Workload("cartpole", 32, 10)]


def simloader_variants(model: mujoco.MjModel) -> dict[str, dict]:
    """SimDataset keywords of each kind of per-step input."""
    body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.nbody - 1)
    return {
        "ctrl": dict(control=controls.Uniform()),
        "ctrl + xfrc_applied": dict(
            control_spec=int(S.mjSTATE_CTRL | S.mjSTATE_XFRC_APPLIED),
            control={"ctrl": controls.Uniform(),
                     "xfrc_applied": controls.Normal(std=1.0, on=body)}),
        "qfrc_applied": dict(control_spec=int(S.mjSTATE_QFRC_APPLIED),
                             control=controls.Normal(std=1.0)),
        "ctrl, randomized dof_damping": dict(
            control=controls.Uniform(),
            randomize=[dr.scale("dof_damping", dr.Uniform(0.8, 1.2))]),
    }


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    args = common.parse(p)
    rows, notes = [], []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        measures: dict[str, Callable[[], float]] = {}
        sims = {}
        for name, kwargs in simloader_variants(model).items():
            sims[name] = bench.SimloaderMeasure(model, w, "mjx", args.seed, impl="warp",
                                                **kwargs)
        o = sims["ctrl"].ds.config.options
        sizes = dict(naconmax=o.naconmax, njmax=o.njmax)
        raws = {"raw, inputs refreshed": bench.RawMjx(model, w, args.seed, impl="warp", **sizes),
                "raw, controls not refreshed": bench.RawMjx(model, w, args.seed, impl="warp",
                                                            refresh=False, **sizes),
                "raw, no controls": bench.RawMjx(model, w, args.seed, impl="warp",
                                                 controls=False, **sizes),
                "raw, inputs refreshed, rows checked": bench.RawMjx(
                    model, w, args.seed, impl="warp", check=True, **sizes)}
        nbatches = common.batches_for(args, raws["raw, inputs refreshed"].batch_s)
        for name, raw in raws.items():
            measures[name] = (lambda raw=raw: raw.measure(1)) if "not" in name else \
                (lambda raw=raw: raw.measure(nbatches))
        for name, sim in sims.items():
            measures[f"simloader: {name}"] = lambda sim=sim: sim.measure(nbatches)
        results = common.interleave(measures, args.repeats, desc=str(w))
        base = results["raw, inputs refreshed"]
        for name, s in results.items():
            rows.append([str(w), name, common.ns(s), common.rate(1 / s), f"{base / s:.3f}"])
        diverged = {name: sim.ds.stats["diverged"] for name, sim in sims.items()}
        notes.append(f"{w}: naconmax={o.naconmax}, njmax={o.njmax}; trajectories flagged "
                     f"diverged by simloader: {diverged}; overflowed: "
                     f"{ {n: s.ds.stats['overflow'] for n, s in sims.items()} }")
    table = common.markdown_table(["workload", "method", "ns/step", "steps/s",
                                   "throughput / raw refreshed"], rows)
    common.report(args, "bench_warp_inputs", "MuJoCo Warp: per-step inputs",
                  [f"Medians of {args.repeats} alternating repetitions.", *notes, table])


if __name__ == "__main__":
    main()
