"""What domain randomization costs: the same workload with and without it, on each backend.

For every workload and backend (`rollout`: MuJoCo's threads on all cores; `mjx`: JAX on the
GPU, or the CPU without one), two simloader datasets do the same work (uniform controls drawn
every batch, state and sensors recorded after every step) and differ only in `randomize`:

  cartpole  the pole's mass scaled in [0.5, 2], damping added to its hinge, the actuator gain
            scaled in [0.5, 2]: three values drawn per trajectory, per batch
  humanoid  every body mass scaled in [0.8, 1.2] (17 values per trajectory; on MJX the
            constants MuJoCo derives from masses are recomputed in the batch function)
  other     every body mass scaled in [0.8, 1.2]

Each is timed as delivered (torch tensors in hand) over `--batches` batches (more if they take
under `--min-seconds`) after a warm-up pass that compiles; the two run alternately in one
process and the medians of `--repeats` repetitions are reported, with the ratio of
throughputs (target: randomized / plain >= 0.95). For MJX, the compilation of each is reported
apart, and a later pass that compiled again is flagged.

    python benchmarks/bench_randomize.py --quick                   # a smoke run on a laptop
    python benchmarks/bench_randomize.py --save --results-dir $OUT # GPU machine: both backends
    python benchmarks/bench_randomize.py --backends mjx --workloads humanoid:16384x200
"""

from __future__ import annotations

import os

# torch shares the GPU (DLPack views, training); JAX must not take 75% of it up front
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import copy  # noqa: E402
import importlib.util  # noqa: E402
from collections.abc import Callable  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import common  # noqa: E402
import simloader  # noqa: E402
from simloader import bench  # noqa: E402
from simloader import randomize as dr  # noqa: E402

BACKENDS = ("cpu", "mjx")
DEFAULT = {"cpu": [common.Workload("cartpole", 8192, 1000),
                       common.Workload("humanoid", 4096, 200)],
           "mjx": [common.Workload("cartpole", 8192, 1000),
                   common.Workload("cartpole", 65536, 1000),
                   common.Workload("humanoid", 16384, 200)]}
QUICK = {"cpu": [common.Workload("cartpole", 256, 100), common.Workload("humanoid", 64, 50)],
         "mjx": [common.Workload("cartpole", 64, 20)]}
TARGET = 0.95  # randomized / plain throughput

HEADERS = ["workload", "nbatch x nstep", "backend", "runs on", "plain ns/step",
           "randomized ns/step", "plain steps/s", "randomized steps/s", "randomized / plain",
           "compile s (plain, randomized)"]


def randomization(name: str, model: mujoco.MjModel) -> list[dr.Param]:
    """The randomization spec of a workload (see the module docstring)."""
    if name == "cartpole":
        pole = model.body(model.nbody - 1).name
        hinge = model.joint(model.njnt - 1).name
        return [dr.scale("body_mass", dr.Uniform(0.5, 2.0), on=pole),
                dr.add("dof_damping", dr.Uniform(0.0, 0.01), on=hinge),
                dr.scale("actuator_gainprm", dr.Uniform(0.5, 2.0), index=0)]
    return [dr.scale("body_mass", dr.Uniform(0.8, 1.2))]


class Measure:
    """A dataset, warmed up by one pass (which compiles), then timed per step."""

    def __init__(self, model: mujoco.MjModel, w: common.Workload, backend: str, seed: int,
                 randomize: list[dr.Param] | None):
        options = {"compilation_cache": False} if backend == "mjx" else {}  # JAX's: off
        self.w = w
        self.ds = simloader.SimDataset(model, backend=backend, nbatch=w.nbatch, nstep=w.nstep,
                                       control=simloader.controls.Uniform(), seed=seed,
                                       randomize=randomize, **options)
        first = common.time_stream(self.ds, 0)
        self.compile_s = self.ds.stats.get("compile_s", 0.0)
        self.first_s = first.first_s

    def __call__(self, nbatches: int) -> float:
        return common.time_stream(self.ds, nbatches).steady_s / (nbatches * self.w.steps)

    def recompiled(self) -> bool:
        return self.ds.stats.get("compiles", 0) > 1


def equivalent_models(model: mujoco.MjModel, spec: list[dr.Param], nbatch: int,
                      seed: int) -> list[mujoco.MjModel]:
    """`nbatch` MjModel copies with values drawn as the spec draws them, constants recomputed:
    what raw `mujoco.rollout` needs to do the randomized work."""
    plan = dr.RandomizationPlan(model, spec)
    values = plan.sample(np.random.SeedSequence(seed), nbatch)
    models = []
    for i in range(nbatch):
        m = copy.copy(model)
        for r in plan.resolved:
            field = getattr(m.opt, r.field[4:]) if r.field.startswith("opt.") else \
                getattr(m, r.field)
            field.reshape(-1)[r.elements] = values[r.param.key][i]
        if plan.setconst:
            mujoco.mj_setConst(m, mujoco.MjData(m))
        models.append(m)
    return models


def runs_on(backend: str) -> str:
    if backend == "cpu":
        return f"{common.cpu_count()} cores"
    import jax
    return jax.devices()[0].device_kind


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT["cpu"] + DEFAULT["mjx"],
                      QUICK["cpu"] + QUICK["mjx"], throughput=True)
    p.add_argument("--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS),
                   help="backends to measure (mjx is skipped where JAX is not installed)")
    p.add_argument("--raw", action="store_true",
                   help="rollout backend: also raw mujoco.rollout on one model and on the "
                        "equivalent list of randomized models")
    args = common.parse(p)
    backends = [b for b in args.backends
                if b != "mjx" or importlib.util.find_spec("mujoco.mjx") is not None]
    if "mjx" in backends:
        import jax
        jax.config.update("jax_enable_compilation_cache", False)  # in-process compiles: cold

    table, notes, counts, specs = [], [], [], {}
    for backend in backends:
        for w in args.workloads or (QUICK if args.quick else DEFAULT)[backend]:
            model = common.load_model(w.name, args.model_dir)
            spec = randomization(w.name, model)
            specs[w.name] = ", ".join(p.key for p in spec)
            plain = Measure(model, w, backend, args.seed, None)
            randomized = Measure(model, w, backend, args.seed, spec)
            nbatches = common.batches_for(args, plain(1) * w.steps)
            counts.append(f"{nbatches} for {w} on {backend}")
            measures: dict[str, Callable[[], float]] = {
                "plain": lambda: plain(nbatches), "randomized": lambda: randomized(nbatches)}
            if backend == "cpu" and args.raw:
                # the same two workloads on raw mujoco.rollout: what per-trajectory models
                # cost MuJoCo itself
                raw_one, _ = bench.raw_rollout(model, w, common.cpu_count(), args.seed)
                raw_list, _ = bench.raw_rollout(
                    equivalent_models(model, spec, w.nbatch, args.seed), w, common.cpu_count(),
                    args.seed)
                measures["raw"] = lambda: raw_one(nbatches)
                measures["raw models"] = lambda: raw_list(nbatches)
            results = common.interleave(measures, args.repeats, desc=f"{w} {backend}")
            if "raw" in results:
                notes.append(f"{w}, raw mujoco.rollout: {common.ns(results['raw'])} ns/step on "
                             f"one model, {common.ns(results['raw models'])} ns/step on "
                             f"{w.nbatch} models randomized alike: per-trajectory models / one "
                             f"model = {results['raw'] / results['raw models']:.3f}")
            ratio = results["plain"] / results["randomized"]
            compile_s = (f"{plain.compile_s:.1f}, {randomized.compile_s:.1f}"
                         if backend == "mjx" else "-")
            table.append([w.name, f"{w.nbatch} x {w.nstep}", backend, runs_on(backend),
                          common.ns(results["plain"]), common.ns(results["randomized"]),
                          common.rate(1 / results["plain"]),
                          common.rate(1 / results["randomized"]), common.ratio(ratio),
                          compile_s])
            if ratio < TARGET:
                notes.append(f"{w} on {backend}: randomized / plain = {ratio:.3f}, below the "
                             f"target {TARGET}")
            for name, m in (("plain", plain), ("randomized", randomized)):
                if m.recompiled():
                    notes.append(f"{w} on {backend}: the {name} dataset compiled "
                                 f"{m.ds.stats.get('compiles', 0)} times (expected once)")
            del plain, randomized, measures

    summary = (f"Medians of {args.repeats} alternating repetitions, each timing batches after a "
               f"warm-up pass ({', '.join(counts)}). Randomized: "
               + "; ".join(f"{name}: {keys}" for name, keys in specs.items())
               + f". Target: randomized / plain >= {TARGET}. On a machine other than the GPU "
               f"host only the ratios mean something.")
    sections = [summary] + notes + [common.markdown_table(HEADERS, table)]
    if args.save:
        common.save(args, "bench_randomize", "The cost of domain randomization", sections)
    print("\n\n".join(sections))


if __name__ == "__main__":
    main()
