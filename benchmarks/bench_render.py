"""Pixels on the MJX backend (MuJoCo Warp): simloader delivering one camera's RGB (uint8) every
step, next to a raw jitted scan doing the same step + render, in one process, alternately.

Raw rows, both `scan(vmap(step))` with MuJoCo Warp's renderer after every step and the same
uint8 unpacking, batch-major outputs:
  raw step+render        renders the poses `mj_step` leaves in the data (those of the step's
                         start), the recipe of MJX's own tests;
  raw step+pose+render   first brings geoms, cameras and lights to the new state (kinematics,
                         camlight), as simloader does so that a frame shows the delivered state:
                         the same work as simloader.
Frames/s counts one image of one world per step.

    python benchmarks/bench_render.py --quick                        # CPU smoke run (Warp CPU)
    python benchmarks/bench_render.py --save --results-dir $OUT      # on the GPU machine
"""

from __future__ import annotations

import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

from collections.abc import Callable  # noqa: E402

import common  # noqa: E402
from simloader import bench  # noqa: E402

DEFAULT = [common.Workload("cartpole", 16384, 50), common.Workload("humanoid", 2048, 50)]
QUICK = [common.Workload("cartpole", 8, 4)]
# the camera and image size of each model (a contact-rich model at 128x128, as peers report)
VIEWS = {"cartpole": ("fixed", 64), "humanoid": ("side", 128)}


def raw_render(model, nbatch: int, camera: str, size: int, pose: bool) -> Callable:
    """`render(mx, d) -> (d, {"rgb": (nbatch, size, size, 3) uint8})` for `bench.RawMjx`."""
    import jax
    import jax.numpy as jnp
    import mujoco
    from simloader.backends.mjx.render import _Pose
    from simloader.backends.mjx.runtime import mjx

    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    context = mjx.create_render_context(mjm=model, nworld=nbatch, cam_active=[cam],
                                       cam_res=[(size, size)], render_rgb=[True],
                                       render_depth=[False], render_seg=[False])
    poses = _Pose(model)

    def render(mx, d):
        ctx = context.pytree()
        if pose:
            d = jax.vmap(poses, (None, 0))(mx, d)
        d = jax.vmap(mjx.refit_bvh, (None, 0, None))(mx, d, ctx)
        packed, _, d = jax.vmap(mjx.render, (None, 0, None))(mx, d, ctx)
        rgb = jnp.stack([(packed >> s) & 0xFF for s in (16, 8, 0)], -1).astype(jnp.uint8)
        return d, {"rgb": rgb.reshape(nbatch, size, size, 3)}

    render.context = context  # kept alive with the function (MJX drops collected contexts)
    return render


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], DEFAULT, QUICK, throughput=True)
    p.add_argument("--size", type=int, help="image height and width (default: per model, "
                   + ", ".join(f"{k} {v[1]}" for k, v in VIEWS.items()) + ")")
    args = common.parse(p)
    import simloader

    rows = []
    for w in common.workloads(args, DEFAULT, QUICK):
        model = common.load_model(w.name, args.model_dir)
        camera, size = VIEWS.get(w.name, (0, 64))
        size = args.size or size
        view = simloader.Camera(camera, height=size, width=size)
        sim = bench.SimloaderMeasure(model, w, "mjx", args.seed, impl="warp",
                                     record=("state", "sensordata", view))
        naconmax, njmax = sim.ds.config.options.naconmax, sim.ds.config.options.njmax
        raws = {name: bench.RawMjx(model, w, args.seed, impl="warp", naconmax=naconmax,
                                   njmax=njmax, render=raw_render(model, w.nbatch, camera, size,
                                                                  pose))
                for name, pose in (("raw step+render", False), ("raw step+pose+render", True))}
        slowest = max([sim.first_s / 10] + [r.batch_s for r in raws.values()])
        nbatches = common.batches_for(args, slowest)
        measures = {name: (lambda r=r: r.measure(nbatches)) for name, r in raws.items()}
        measures["simloader"] = lambda s=sim: s.measure(nbatches)
        results = common.interleave(measures, args.repeats, desc=f"{w} {size}x{size}")
        for name, s in results.items():
            rows.append([f"{w}", f"{camera} {size}x{size}", name, common.rate(1 / s),
                         f"{results['raw step+render'] / s:.3f}",
                         f"{results['raw step+pose+render'] / s:.3f}"])
        del sim, raws
    table = common.markdown_table(["workload", "camera", "what", "frames/s",
                                   "vs raw step+render", "vs raw step+pose+render"], rows)
    common.report(args, "bench_render", "Pixels on MJX (MuJoCo Warp)",
                  [f"Medians of {args.repeats} alternating repetitions; simloader delivered "
                   f"throughput (torch tensors in hand): RGB uint8 of one camera every step, "
                   f"with state and sensordata.", table])


if __name__ == "__main__":
    main()
