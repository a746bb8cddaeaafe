"""Closed loop on MJX: a torch MLP (2 x 256) picks every step's controls from `(qpos, qvel)`,
next to the same MLP fused in JAX inside the scan (the upper bound), a raw torch-per-step loop
without simloader, and open-loop simulation, in one process, alternately.

Rows (every one records the state after each step and the controls):
  open loop              simloader, per-step uniform controls (no policy)
  fused JAX MLP          raw: the MLP in JAX inside one jitted scan
  raw torch per step     raw: jitted single steps, the torch MLP between them, DLPack both ways
  raw Warp graph + torch raw (impl warp, GPU): MuJoCo Warp's step as one CUDA graph replayed
                         on torch's stream, the torch MLP between replays, nothing else (the
                         scheme simloader's Warp closed loop uses, without its checks)
  simloader policy=      simloader, the torch MLP as `policy=`
  ... + camera           with --camera: open loop and policy= also rendering a camera's RGB
                         every step (handed to the policy, which ignores it)

    python benchmarks/bench_policy_mjx.py --quick                      # CPU smoke run
    python benchmarks/bench_policy_mjx.py --save --results-dir $OUT    # on the GPU machine
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import closed_loop_baselines as baselines  # noqa: E402
import common  # noqa: E402
import simloader  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("humanoid", 8192, 200), common.Workload("cartpole", 4096, 200)]
QUICK = [common.Workload("cartpole", 8, 10)]
# the implementations to run per model: the humanoid (contacts) on Warp; the cart-pole on both
IMPLS = {"humanoid": ("warp",), "cartpole": ("jax", "warp")}
GRAPH = "raw Warp graph + torch"
CAMERA_OPEN, CAMERA_POLICY = "open loop + camera", "simloader policy= + camera"


# simloader's engine for each implementation the raw baselines name (MJX's own words)
ENGINE = {"jax": "mjx", "warp": "warp"}


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--impls", nargs="+", choices=("jax", "warp"),
                   help="MJX implementations (default: per model, " + ", ".join(
                       f"{k} {'+'.join(v)}" for k, v in IMPLS.items()) + ")")
    p.add_argument("--hidden", type=int, default=256, help="units per hidden layer")
    p.add_argument("--camera", metavar="NAME:HxW",
                   help="also time open loop and policy= recording this camera's RGB every "
                        "step (the policy is handed the images; Warp only)")
    args = common.parse(p)
    import torch

    device = "cuda" if torch.cuda.is_available() else "cpu"
    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        net = baselines.mlp(model.nq + model.nv, model.nu, args.hidden, args.seed).to(device)
        policy = baselines.StatePolicy(net, model)
        # (MuJoCo Warp's engine needs a CUDA GPU: left out by default where there is none)
        default = [i for i in IMPLS.get(w.name, ("jax",)) if i != "warp" or device == "cuda"]
        for impl in args.impls or default:
            sims = {
                "open loop": bench.SimloaderMeasure(model, w, ENGINE[impl], args.seed,
                                                    record=("state",)),
                "simloader policy=": bench.SimloaderMeasure(
                    model, w, ENGINE[impl], args.seed, control=None, policy=policy,
                    record=("state", "qpos", "qvel")),
            }
            if args.camera and impl == "warp":
                name, size = args.camera.split(":")
                height, width = (int(x) for x in size.split("x"))
                camera = simloader.Camera(name, height=height, width=width)
                sims[CAMERA_OPEN] = bench.SimloaderMeasure(
                    model, w, ENGINE[impl], args.seed, record=("state", camera))
                sims[CAMERA_POLICY] = bench.SimloaderMeasure(
                    model, w, ENGINE[impl], args.seed, control=None, policy=policy,
                    record=("state", "qpos", "qvel", camera))
            options = sims["open loop"].ds.config.options
            # MuJoCo Warp's buffer sizes as simloader resolved them (none on MJX-JAX)
            sizes = {k: getattr(options, k, None) for k in ("naconmax", "njmax")}
            raws = {name: baselines.RawClosedLoopMjx(model, w, net, mode, impl=impl, **sizes)
                    for name, mode in (("fused JAX MLP", "fused"),
                                       ("raw torch per step", "torch"))}
            if impl == "warp" and device == "cuda":
                raws[GRAPH] = baselines.RawWarpGraphLoop(model, w, net, **sizes)
            slowest = max([s.first_s / 10 for s in sims.values()]
                          + [r.measure(1) * w.steps for r in raws.values()])
            nbatches = common.batches_for(args, slowest)
            measures = {name: (lambda r=r: r.measure(nbatches)) for name, r in raws.items()}
            measures.update({name: (lambda s=s: s.measure(nbatches))
                             for name, s in sims.items()})
            results = common.interleave(measures, args.repeats, desc=f"{w} {impl}")
            for name in ("open loop", "fused JAX MLP", "raw torch per step", GRAPH,
                         "simloader policy=", CAMERA_OPEN, CAMERA_POLICY):
                if name not in results:
                    continue
                s = results[name]
                rows.append([str(w), impl, name, common.ns(s), common.rate(1 / s),
                             f"{results['fused JAX MLP'] / s:.3f}",
                             f"{results['open loop'] / s:.3f}"])
            del sims, raws
    table = common.markdown_table(["workload", "impl", "what", "ns/step", "steps/s",
                                   "vs fused JAX MLP", "vs open loop"], rows)
    common.report(args, "bench_policy_mjx", "Closed loop on MJX: a torch MLP per step",
                  [f"Medians of {args.repeats} alternating repetitions; delivered throughput "
                   f"(tensors in hand, state and controls of every step). Policy: MLP "
                   f"{args.hidden}x{args.hidden} (tanh) of (qpos, qvel), torch on {device}.",
                   table])


if __name__ == "__main__":
    main()
