"""What the CPU renderer's quality switches buy: `Camera(shadows=False, multisample=False)`
against the default, frames per second of a stream on MuJoCo Menagerie's Go1 scene (the copy
in tests/robots: 4096-pixel shadow maps, multisampling), 64 x 64, alternately in one process.

    python benchmarks/bench_render_quality.py --save
"""

from __future__ import annotations

import argparse
import statistics
import time

import common
import simloader

SCENE = common.REPO / "tests" / "robots" / "unitree_go1" / "scene.xml"


def frames_per_second(shadows: bool, multisample: bool, batches: int) -> float:
    cam = simloader.Camera(-1, height=64, width=64, shadows=shadows, multisample=multisample)
    ds = simloader.SimDataset(str(SCENE), backend="cpu", nbatch=4, nstep=10,
                              num_batches=batches + 1, record=("state", cam), nthread=1)
    it = iter(ds)
    next(it)  # warm: renderers made
    start, n = time.perf_counter(), 0
    for batch in it:
        n += batch["camera/free/rgb"].shape[0] * batch["camera/free/rgb"].shape[1]
    return n / (time.perf_counter() - start)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--batches", type=int, default=3)
    common.add_output_options(p)
    args = p.parse_args()
    variants = {"default (shadows, multisampling)": (True, True),
                "shadows=False, multisample=False": (False, False)}
    got = {name: [] for name in variants}
    for rep in range(args.repeats):
        for name in (variants if rep % 2 == 0 else reversed(list(variants))):
            got[name].append(frames_per_second(*variants[name], args.batches))
    base = statistics.median(got["default (shadows, multisampling)"])
    rows = [[name, f"{statistics.median(v):.1f}", f"{statistics.median(v) / base:.1f}x"]
            for name, v in got.items()]
    table = common.markdown_table(["Camera", "frames/s", "against the default"], rows)
    common.report(args, "bench_render_quality", "The CPU renderer's quality switches",
                  [f"Go1 scene of tests/robots, 64 x 64, 4 x 10 frames a batch, one thread; "
                   f"medians of {args.repeats} alternating repeats of {args.batches} batches.",
                   table])


if __name__ == "__main__":
    main()
