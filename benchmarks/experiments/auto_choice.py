"""Does `backend="auto"` pick the fastest engine? Every engine that runs here, measured on a
table of models and sizes, next to auto's choice and the rule's estimates.

Rows: the built-in cart-pole (contact-free), the built-in humanoid (contacts) and the
cart-pole with a 64x64 RGB camera (`Camera("front")`), each at nbatch 64, 1024 and 8192.
Each engine is timed through simloader as delivered (`simloader.bench.SimloaderMeasure`:
a warm-up pass, which compiles on MJX, then the median of `--repeats` passes of `--batches`
batches, tensors in hand). Its start-up (construction to the first batch in hand, MJX with an
empty compilation cache: a first run's) is timed too, since `auto` judges an endless stream by
the steps of its first minute, start-up included (`auto.FIRST_MINUTE_S`): "best" is the engine
that delivers most in that minute. The camera rows run fewer steps (`--camera-nstep`), since every
step renders `nbatch` images. Also printed: each model's single-core step time and the rule's
estimate per engine (`simloader/backends/auto.py`), the numbers the rule is fitted to.

  python benchmarks/experiments/auto_choice.py --save --results-dir $OUT  # GPU machine
  python benchmarks/experiments/auto_choice.py --nstep 20 --save          # 2-core machine
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import sys
import tempfile
import time

# benchmarks/ on the path: `common` is there, one folder up from these experiments
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import common  # noqa: E402
from common import markdown_table  # noqa: E402

import simloader  # noqa: E402
from simloader import threads  # noqa: E402
from simloader import bench  # noqa: E402
from simloader import backends  # noqa: E402
from simloader.backends import auto  # noqa: E402
from simloader.backends.contract import Job  # noqa: E402

SIZES = (64, 1024, 8192)


def rows(args):
    for name in args.models:
        camera = name.endswith("+camera")
        model = simloader.load_model(name.removesuffix("+camera"))
        record = (("state", simloader.Camera("front")) if camera else ("state", "sensordata"))
        for nbatch in args.sizes:
            yield name, model, record, nbatch, args.camera_nstep if camera else args.nstep


def measure(model, record, nbatch, nstep, engine, args) -> tuple[float, float]:
    """(steps/s, start-up seconds) of `engine` through simloader: the median of `--repeats`
    timed passes, and construction to the first batch in hand (a cold MJX compilation)."""
    w = bench.Workload("m", nbatch, nstep)
    # one empty cache for the run (JAX takes the first directory it is given): every row
    # compiles a program of its own, so each MJX start-up is a first run's
    options = {"compilation_cache": args.cache} if engine == "mjx" else {}
    start = time.perf_counter()
    sim = bench.SimloaderMeasure(model, w, engine, seed=0, record=record, **options)
    startup = time.perf_counter() - start
    try:
        rates = [1 / sim.measure(args.batches) for _ in range(args.repeats)]
    finally:
        del sim
        gc.collect()
    return statistics.median(rates), startup


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["cartpole", "humanoid", "cartpole+camera"])
    p.add_argument("--sizes", nargs="+", type=int, default=list(SIZES))
    p.add_argument("--nstep", type=int, default=100)
    p.add_argument("--camera-nstep", type=int, default=10)
    p.add_argument("--batches", type=int, default=3)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--engines", nargs="+", default=None,
                   help="default: every engine that runs here (MJX on the CPU included)")
    common.add_output_options(p)
    args = p.parse_args()
    # JAX's compilation cache for the run's MJX rows, empty at the start, removed at the end
    with tempfile.TemporaryDirectory(prefix="auto-choice-jax-") as args.cache:
        compare(args)


def compare(args: argparse.Namespace) -> None:
    """Every row: auto's choice, each engine measured, the tables and the plot."""
    can = auto.candidates()
    engines = args.engines or ["cpu", "warp", "mjx"]
    engines = [e for e in engines if not can.get(e) or (e == "mjx" and "JAX has no GPU"
                                                        in can["mjx"])]
    cores = threads.available_cpus()
    table, records = [], []
    for name, model, record, nbatch, nstep in rows(args):
        ds = simloader.SimDataset(model, backend="auto", nbatch=nbatch, nstep=nstep,
                                  record=record, control=simloader.controls.Uniform())
        chosen, reason = ds.config.backend, ds.config.backend_reason
        del ds
        contacts = auto.has_contacts(model)
        step_s = auto.cpu_step_seconds(model)
        measured, startup = {}, {}
        for engine in engines:
            if engine == "mjx" and name.endswith("+camera"):
                continue  # MJX does not render
            start = time.perf_counter()
            try:
                measured[engine], startup[engine] = measure(model, record, nbatch, nstep,
                                                            engine, args)
            except (ValueError, RuntimeError) as e:
                print(f"{name} {nbatch} {engine}: {e}", file=sys.stderr)
            print(f"{name} nbatch={nbatch} {engine}: {measured.get(engine, 0) / 1e6:.3f}M "
                  f"steps/s, start-up {startup.get(engine, 0):.1f} s "
                  f"({time.perf_counter() - start:.0f} s)", file=sys.stderr, flush=True)
        minute = {e: auto.first_minute_steps(measured[e], startup[e]) for e in measured}
        fastest = max(measured, key=measured.get)
        best = max(minute, key=minute.get)
        job = Job(step_s=step_s, nbatch=nbatch, contacts=contacts, cores=cores, policy=False,
                  cameras=name.endswith("+camera"))
        estimates = {e: backends.engine(e).estimate(job) for e in measured}
        ratio = minute.get(chosen, 0) / minute[best]
        records.append({"model": name, "nbatch": nbatch, "nstep": nstep, "contacts": contacts,
                        "step_s": step_s, "measured": measured, "startup_s": startup,
                        "first_minute_steps": minute, "estimates": estimates,
                        "auto": chosen, "fastest": fastest, "best": best, "reason": reason})
        table.append([name, nbatch, nstep] + [
            f"{measured[e] / 1e6:.3f}M, {startup[e]:.1f} s" if e in measured else "-"
            for e in engines] + [
            chosen, fastest, best, f"{ratio:.2f}", "yes" if chosen == best or ratio >= auto.NEAR_TIE
            else "**NO**"])
    headers = (["model", "nbatch", "nstep"] + [f"{e} steps/s, start-up" for e in engines]
               + ["auto chose", "fastest steady", "most in a first minute",
                  "auto / most", "auto right"])
    fits = [[r["model"], r["nbatch"], f"{r['step_s'] * 1e6:.2f} us", r["contacts"]] + [
        f"{r['estimates'][e] / 1e6:.3f}M" if e in r["estimates"] else "-" for e in engines]
        for r in records]
    sections = [
        "## auto's choice against every engine, measured through simloader\n\n"
        + markdown_table(headers, table),
        "'auto right': auto chose the engine that delivers most in an endless stream's first "
        "minute (steady steps/s x (60 s - start-up)), or one within the rule's near tie of it "
        f"({auto.NEAR_TIE:.0%}: a near tie goes to the engine that starts first). Start-up: "
        "construction to the first batch in hand, MJX compiling into an empty cache.",
        "## the rule's inputs and estimates (simloader/backends/auto.py)\n\n"
        + markdown_table(["model", "nbatch", "1-core step", "contacts"]
                         + [f"{e} estimate" for e in engines], fits),
        "## raw records\n\n```json\n" + json.dumps(records, indent=1) + "\n```",
    ]
    common.report(args, "auto_choice", f"backend='auto' against every engine ({cores} cores, "
                                       f"{common.environment()['GPU']})", sections)
    plot(args, records, engines)


def plot(args, records, engines) -> None:
    if not args.save:
        return
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    models = list(dict.fromkeys(r["model"] for r in records))
    fig, axes = plt.subplots(1, len(models), figsize=(4.5 * len(models), 3.8), squeeze=False)
    for ax, name in zip(axes[0], models):
        mine = [r for r in records if r["model"] == name]
        for engine in engines:
            pts = [(r["nbatch"], r["measured"][engine]) for r in mine if engine in r["measured"]]
            if pts:
                ax.plot(*zip(*pts), marker="o", label=engine)
        for r in mine:
            ax.scatter([r["nbatch"]], [r["measured"].get(r["auto"], 0)], s=160,
                       facecolors="none", edgecolors="black", zorder=3)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("trajectories per batch")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("steps/s (circled: auto's choice)")
    axes[0][0].legend()
    fig.tight_layout()
    common.save_figure(args, "auto_choice", fig)


if __name__ == "__main__":
    main()
