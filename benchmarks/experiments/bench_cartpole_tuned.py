"""The built-in cart-pole against the dm_control cart-pole that MuJoCo Playground tunes for
accelerators, on MJX at the same sizes, through simloader and as a raw jitted loop.

The built-in model carries Playground's solver options (`iterations="1"
ls_iterations="4"`, contacts and Euler damping off); it keeps its own sensors and camera.
The issue's bar: the built-in cart-pole on MJX runs at least 0.9x the dm_control
cart-pole's steps/s at 8192 trajectories. Measured alternately in one process (medians).

  python benchmarks/experiments/bench_cartpole_tuned.py --model-dir .models/dm_control --save \\
      --results-dir $OUT
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
from common import markdown_table  # noqa: E402

import simloader  # noqa: E402
from simloader import bench  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", type=pathlib.Path, default=None)
    p.add_argument("--nbatch", type=int, default=8192)
    p.add_argument("--nstep", type=int, default=1000)
    p.add_argument("--batches", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    common.add_output_options(p)
    args = p.parse_args()
    w = bench.Workload("cartpole", args.nbatch, args.nstep)
    models = {"built-in cartpole": simloader.load_model("cartpole"),
              "dm_control cartpole (Playground)": common.load_model("cartpole", args.model_dir)}
    measures = {}
    for name, model in models.items():
        sim = bench.SimloaderMeasure(model, w, "mjx", seed=0)
        raw = bench.RawMjx(model, w, seed=0)
        measures[f"simloader mjx, {name}"] = lambda sim=sim: sim.measure(args.batches)
        measures[f"raw MJX, {name}"] = lambda raw=raw: raw.measure(args.batches)
    s_per_step = common.interleave(measures, args.repeats, desc=str(w))
    rows = [[name, f"{args.nbatch} x {args.nstep}", common.rate(1 / s)]
            for name, s in s_per_step.items()]
    ours = 1 / s_per_step["simloader mjx, built-in cartpole"]
    theirs = 1 / s_per_step["simloader mjx, dm_control cartpole (Playground)"]
    raw_ours = 1 / s_per_step["raw MJX, built-in cartpole"]
    raw_theirs = 1 / s_per_step["raw MJX, dm_control cartpole (Playground)"]
    sections = [markdown_table(["method, model", "nbatch x nstep", "steps/s"], rows),
                f"built-in / dm_control through simloader: **{ours / theirs:.2f}x** "
                f"(raw MJX: {raw_ours / raw_theirs:.2f}x); the bar is 0.9x."]
    common.report(args, "bench_cartpole_tuned", "The built-in cart-pole on MJX next to "
                                                "Playground's dm_control cart-pole", sections)


if __name__ == "__main__":
    main()
