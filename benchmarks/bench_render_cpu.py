"""Pixels on the rollout backend: simloader simulating and rendering one camera every step,
next to raw `mujoco.Renderer` threads rendering the same states (one renderer per thread, the
same number of threads, `mj_setState` + `mj_forward` + `update_scene` + `render` per frame),
in one process, alternately. Frames/s counts one image of one trajectory.

    python benchmarks/bench_render_cpu.py --quick                        # smoke run
    python benchmarks/bench_render_cpu.py --save --results-dir $OUT      # 16 threads, GPU host
"""

from __future__ import annotations

import os

# the raw renderers are plain mujoco.Renderer: MuJoCo reads its GL platform at import
os.environ.setdefault("MUJOCO_GL", "egl")

import time  # noqa: E402

import common  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("cartpole", 512, 50)]
QUICK = [common.Workload("cartpole", 8, 4)]
VIEWS = {"cartpole": "fixed", "humanoid": "side"}


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--threads", type=int, default=min(16, os.cpu_count() or 1),
                   help="simulation threads of simloader and raw render threads")
    p.add_argument("--size", type=int, default=64, help="image height and width")
    args = common.parse(p)
    import simloader

    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        camera = VIEWS.get(w.name, 0)
        view = simloader.Camera(camera, height=args.size, width=args.size)
        sim = bench.SimloaderMeasure(model, w, "cpu", args.seed, nthread=args.threads,
                                     record=("state", view))
        states = next(iter(sim.ds))["state"].numpy()
        raw = bench.RawRenderers(model, camera, args.size, args.threads)
        raw(states)  # makes its renderers
        plain = bench.SimloaderMeasure(model, w, "cpu", args.seed, nthread=args.threads,
                                       record=("state",))

        def raw_measure(n: int) -> float:
            start = time.perf_counter()
            for _ in range(n):
                raw(states)
            return (time.perf_counter() - start) / (n * w.steps)

        nbatches = common.batches_for(args, raw_measure(1) * w.steps)
        results = common.interleave({
            "raw Renderer threads": lambda: raw_measure(nbatches),
            "simloader (simulate + render)": lambda: sim.measure(nbatches),
            "simloader, no camera": lambda: plain.measure(nbatches)},
            args.repeats, desc=f"{w} {args.size}x{args.size}")
        base = results["raw Renderer threads"]
        for name, s in results.items():
            rows.append([str(w), f"{camera} {args.size}x{args.size}", name, common.rate(1 / s),
                         f"{base / s:.3f}"])
        del sim, plain
        raw.pool.shutdown()  # its threads' renderers go with them
    table = common.markdown_table(["workload", "camera", "what", "frames/s",
                                   "vs raw Renderer threads"], rows)
    common.report(args, "bench_render_cpu", "Pixels on the rollout backend",
                  [f"Medians of {args.repeats} alternating repetitions, {args.threads} threads, "
                   f"MUJOCO_GL={os.environ['MUJOCO_GL']}; 'simloader, no camera' is "
                   f"simulation alone, for context.", table])


if __name__ == "__main__":
    main()
