"""Menagerie robots on the GPU engines, one table: per robot and engine, whether the engine
simulates it, the first batch cold and warm next to the raw engine's, and steps/s next to the
raw engine doing the same work.

The robots are the Menagerie scenes the tests carry (`tests/robots`, collision geometry only).
For each (robot, engine) the engine accepts (`Engine.refuses_model`; a refusal is a row too):

1. First batch: fresh processes, as `benchmarks/bench_startup.py` runs them
   (`simloader.bench.startup`). Cold: raw and simloader at the same time, each with an empty
   cache root of its own, so that both see the same machine; `--jobs` pairs side by side
   (MuJoCo Warp compiles on one CPU core a process): cold seconds are those of a busy machine,
   compared fairly. Warm: then one process at a time on the same roots, raw and simloader
   alternating, `--repeats` each. simloader's share is its seconds after `import torch` less
   the raw script's.
2. Steady state, one (robot, engine) at a time, in a child whose caches are the simloader
   side's of step 1 (warm): `simloader.bench.compare` at NBATCHxNSTEP, simloader and the raw
   engine alternating (`RawWarp`, `RawMjx`: same work), medians.

Every child's result is appended to `robots[-TAG]-DATE.jsonl` as it comes (a run cut short
keeps what it measured); the table is rendered from those lines.

Run on the GPU machine from the repository root:
  python benchmarks/bench_robots.py --jobs 14 --save --results-dir $OUT
  python benchmarks/bench_robots.py --phase steady --cache-root ROOT --lines FILE --save --results-dir $OUT
Smoke run without a GPU (MJX on the CPU, tiny):
  python benchmarks/bench_robots.py --engines mjx --robots universal_robots_ur5e --nbatch 4 \
      --nstep 5 --repeats 1
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import pathlib
import statistics
import subprocess
import sys
import tempfile
from typing import Any, Optional

import common
import mujoco

from simloader.bench.startup import RAW_SCRIPT, SIMLOADER, child_env, run_child

ROBOTS = common.REPO / "tests" / "robots"
ENGINES = ("warp", "mjx")
TARGET = 0.97  # steps/s against the raw engine's, same work (issue 64)


def robots() -> list[str]:
    return sorted(p.name for p in ROBOTS.iterdir() if (p / "scene.xml").is_file())


def refusal(robot: str, engine: str) -> Optional[str]:
    """Why `engine` does not simulate `robot` here (None: it does)."""
    from simloader.backends import engine as entry
    e = entry(engine)
    missing = e.missing()
    if missing is not None:
        return f"cannot run here: {missing}"
    why = e.refuses_model(mujoco.MjModel.from_xml_path(str(ROBOTS / robot / "scene.xml")))
    return None if why is None else f"refuses: {why}"


def roots(cache_root: pathlib.Path, robot: str, engine: str) -> dict[str, pathlib.Path]:
    return {who: cache_root / f"{robot}-{engine}-{who}" for who in ("raw", "simloader")}


def first_batch(robot: str, engine: str, who: str, kind: str, args: argparse.Namespace,
                record: Any) -> None:
    """One fresh process to its first batch: `who` (raw or simloader), caches `kind`."""
    spec = {"model": str(ROBOTS / robot / "scene.xml"), "nbatch": args.nbatch,
            "nstep": args.nstep, "seed": 0, "backend": engine}
    folder = roots(args.cache_root, robot, engine)[who]
    if kind == "cold":
        folder.mkdir(parents=True, exist_ok=False)  # cold for real: a fresh folder
    script = SIMLOADER if who == "simloader" else RAW_SCRIPT[engine]
    r = run_child(script, folder, dict(spec, jax_cache=str(folder / "jax")),
                  who == "simloader", args.timeout)
    record({"phase": "first", "robot": robot, "engine": engine, "who": who, "kind": kind,
            **{k: r.get(k) for k in ("total", "after_torch", "wall", "phases", "error")}})


def cold_pair(robot: str, engine: str, args: argparse.Namespace, record: Any) -> None:
    """Raw and simloader cold at the same time: whatever else runs beside them (other
    robots' pairs, with `--jobs`), both see it."""
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        for f in [pool.submit(first_batch, robot, engine, who, "cold", args, record)
                  for who in ("raw", "simloader")]:
            f.result()


STEADY = r'''
import json, sys
sys.path.insert(0, sys.argv[1])
import mujoco
from simloader.bench.compare import compare
from simloader.bench.raw import Workload, RAW_OF
path, engine, nbatch, nstep, repeats = sys.argv[2], sys.argv[3], *map(int, sys.argv[4:])
model = mujoco.MjModel.from_xml_path(path)
s, _, notes = compare(model, Workload("scene", nbatch, nstep), [engine], repeats=repeats,
                      min_batches=3, min_seconds=1.0, python_steps=100)
print(json.dumps({"s_per_step": s, "notes": notes}))
'''


def steady(robot: str, engine: str, args: argparse.Namespace, record: Any) -> None:
    """Step 2 for one (robot, engine), in a child on the simloader side's warm caches."""
    where = roots(args.cache_root, robot, engine)["simloader"]
    env = child_env(where, {}, simloader=True)
    cmd = [sys.executable, "-c", STEADY, str(common.REPO), str(ROBOTS / robot / "scene.xml"),
           engine, str(args.nbatch), str(args.nstep), str(args.repeats)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=args.timeout)
    lines = [x for x in proc.stdout.splitlines() if x.startswith("{")]
    out = (json.loads(lines[-1]) if proc.returncode == 0 and lines
           else {"error": f"exit {proc.returncode}\n{proc.stderr[-2000:]}"})
    record({"phase": "steady", "robot": robot, "engine": engine, **out})


def median(xs: list) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def summaries(lines: list[dict]) -> list[dict[str, Any]]:
    """Per (robot, engine), from the JSON lines: `refused` (why, or None); first batches
    (`cold`, `warm`: {"simloader", "raw"} seconds from the process start, medians; None where
    none came); simloader's `share` of each (its seconds after `import torch` less the raw
    script's); steady state `rate`, `raw_rate` (steps/s), `ratio`, or `steady_failed`."""
    from simloader.bench.raw import raw_baseline
    lines = [x for x in lines if x["phase"] != "machine"]
    out = []
    for robot, engine in sorted({(x["robot"], x["engine"]) for x in lines}):
        mine = [x for x in lines if (x["robot"], x["engine"]) == (robot, engine)]
        row: dict[str, Any] = {"robot": robot, "engine": engine, "refused": next(
            (x["refused"] for x in mine if x["phase"] == "refused"), None)}

        def first(who: str, kind: str, field: str = "total") -> Optional[float]:
            return median([x.get(field) for x in mine if x["phase"] == "first"
                           and x["who"] == who and x["kind"] == kind and not x.get("error")])

        for kind in ("cold", "warm"):
            row[kind] = {who: first(who, kind) for who in ("simloader", "raw")}
            sim, raw = (first(who, kind, "after_torch") for who in ("simloader", "raw"))
            row[f"share_{kind}"] = None if sim is None or raw is None else sim - raw
        row["rate"] = row["raw_rate"] = row["ratio"] = None
        st = next((x for x in mine if x["phase"] == "steady"), None)
        row["steady_failed"] = st is not None and "s_per_step" not in st
        if st is not None and "s_per_step" in st:
            Raw = raw_baseline(engine)
            s = st["s_per_step"]
            if Raw.row in s and Raw.simloader_row in s:
                row["rate"], row["raw_rate"] = 1 / s[Raw.simloader_row], 1 / s[Raw.row]
                row["ratio"] = s[Raw.row] / s[Raw.simloader_row]
        out.append(row)
    return out


def table(lines: list[dict]) -> str:
    """One row per (robot, engine) from the JSON lines."""
    rows = []
    for r in summaries(lines):
        if r["refused"] is not None:
            rows.append([r["robot"], r["engine"], r["refused"][:100], *["-"] * 7])
            continue

        def pair(kind: str) -> str:
            sim, raw = r[kind]["simloader"], r[kind]["raw"]
            return "failed" if sim is None or raw is None else f"{sim:.1f} / {raw:.1f}"

        def share(kind: str) -> str:
            x = r[f"share_{kind}"]
            return "-" if x is None else f"{x:+.2f}"

        rate = "failed" if r["steady_failed"] else (
            "-" if r["rate"] is None else f"{r['rate'] / 1e6:.2f}M")
        raw_rate = "-" if r["raw_rate"] is None else f"{r['raw_rate'] / 1e6:.2f}M"
        ratio = "-" if r["ratio"] is None else (
            f"{r['ratio']:.3f} ({'yes' if r['ratio'] >= TARGET else '**no**'})")
        rows.append([r["robot"], r["engine"], "accepts", pair("cold"), share("cold"),
                     pair("warm"), share("warm"), rate, raw_rate, ratio])
    headers = ["robot", "engine", "engine's verdict", "first batch cold, s: simloader / raw",
               "simloader's share cold, s", "first batch warm, s: simloader / raw",
               "simloader's share warm, s", "steps/s simloader", "steps/s raw",
               f"ratio (>= {TARGET})"]
    return common.markdown_table(headers, rows)


def plot(lines: list[dict], title: str) -> Any:
    """Three panels, one row per (robot, engine) the engine accepts: steps/s against the raw
    engine (the target marked), and the first batch cold and warm, simloader beside raw."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = [r for r in summaries(lines) if r["refused"] is None]
    names = [f"{r['robot']} ({r['engine']})" for r in rows]
    y = np.arange(len(rows))
    fig, axes = plt.subplots(1, 3, figsize=(15, 0.35 * len(rows) + 1.8), sharey=True)
    ratios = [r["ratio"] if r["ratio"] is not None else 0.0 for r in rows]
    axes[0].barh(y, ratios, color=["tab:blue" if x >= TARGET else "tab:red" for x in ratios])
    axes[0].axvline(TARGET, color="black", lw=1.2)
    for i, r in enumerate(rows):
        axes[0].annotate(" not measured" if r["ratio"] is None else f" {r['ratio']:.3f}",
                         (ratios[i], i), va="center", fontsize=7)
    axes[0].set_xlim(0, 1.25)
    axes[0].set_xlabel(f"steps/s, simloader / raw engine (line: {TARGET})")
    for ax, kind in zip(axes[1:], ("cold", "warm")):
        for offset, who, color in ((-0.2, "simloader", "tab:blue"), (0.2, "raw", "tab:gray")):
            values = [r[kind][who] or 0.0 for r in rows]
            ax.barh(y + offset, values, height=0.4, color=color, label=who)
        ax.set_xlabel(f"first batch {kind}, s from the process start")
        ax.legend(fontsize=7, loc="lower right")
    axes[0].set_yticks(y, names, fontsize=7)
    axes[0].invert_yaxis()
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--robots", nargs="+", choices=robots(), default=robots())
    p.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES))
    p.add_argument("--nbatch", type=int, default=4096)
    p.add_argument("--nstep", type=int, default=100)
    p.add_argument("--phase", choices=("all", "first", "steady", "report"), default="all",
                   help="first batches, steady state, both (steady reuses --cache-root), or "
                        "only the table of the JSON lines already written")
    p.add_argument("--note", action="append", default=[],
                   help="a paragraph printed (and saved) under the table")
    p.add_argument("--jobs", type=int, default=1,
                   help="(robot, engine) start-up runs side by side")
    p.add_argument("--repeats", type=int, default=1,
                   help="warm first-batch pairs; repetitions of the steady state")
    p.add_argument("--timeout", type=float, default=400.0, help="seconds per child")
    p.add_argument("--cache-root", type=pathlib.Path,
                   help="a new folder for the children's caches (default: a fresh temporary "
                        "folder); --phase steady: the one the first phase used")
    p.add_argument("--lines", type=pathlib.Path,
                   help="the JSON-lines file to append to and render (default: "
                        "RESULTS_DIR/robots[-TAG]-DATE.jsonl with --save or for a steady "
                        "phase or a report, else a new temporary file: a run without --save "
                        "writes nothing into the results folder); a steady phase or a report "
                        "on another day names the first phase's")
    common.add_output_options(p)
    args = p.parse_args()
    if args.phase == "steady" and (args.cache_root is None or not args.cache_root.is_dir()):
        # its children would compile every robot cold (minutes each on a GPU machine)
        raise SystemExit("--phase steady: give --cache-root, the folder the first phase "
                         "filled (warm caches)")
    if args.cache_root is None:
        args.cache_root = pathlib.Path(tempfile.mkdtemp(prefix="bench_robots-"))
    elif args.phase in ("all", "first") and args.cache_root.exists():
        raise SystemExit(f"--cache-root: {args.cache_root} exists; give a new folder (its "
                         f"first batches must start cold)")
    if args.lines is not None:
        lines_path = args.lines
    elif args.save or args.phase in ("steady", "report"):
        lines_path = common.result_path(args, "robots", ".jsonl")
    else:
        lines_path = pathlib.Path(tempfile.mkdtemp(prefix="bench_robots-lines-")) / "robots.jsonl"
        print(f"JSON lines (without --save, not kept in the results folder): {lines_path}",
              file=sys.stderr)
    lines_path.parent.mkdir(parents=True, exist_ok=True)

    def record(line: dict) -> None:
        with open(lines_path, "a") as f:
            f.write(json.dumps(line) + "\n")

    if args.phase != "report":  # the machine the lines were measured on, for the report
        record({"phase": "machine", **common.environment()})
    jobs = []
    for robot in args.robots if args.phase != "report" else []:
        for engine in args.engines:
            why = refusal(robot, engine)
            if why is not None:
                record({"phase": "refused", "robot": robot, "engine": engine, "refused": why})
            else:
                jobs.append((robot, engine))
    if args.phase in ("all", "first"):
        with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
            done = [pool.submit(cold_pair, r, e, args, record) for r, e in jobs]
            for f in common.progress(concurrent.futures.as_completed(done), "cold pairs",
                                     total=len(done)):
                f.result()
        # warm runs one at a time, the machine otherwise idle, raw and simloader alternating
        warm = [(r, e, who) for rep in range(args.repeats) for r, e in jobs
                for who in (("raw", "simloader") if rep % 2 == 0 else ("simloader", "raw"))]
        for robot, engine, who in common.progress(warm, "warm runs"):
            first_batch(robot, engine, who, "warm", args, record)
    if args.phase in ("all", "steady"):
        written = [json.loads(x) for x in lines_path.read_text().splitlines()]
        warm = {(x["robot"], x["engine"]) for x in written if x["phase"] == "first"
                and x["who"] == "simloader" and x["kind"] == "warm" and not x.get("error")}
        for robot, engine in common.progress(jobs, "steady state"):
            if (robot, engine) in warm:  # else its first batch failed: nothing warm to time
                steady(robot, engine, args, record)
    lines = [json.loads(x) for x in lines_path.read_text().splitlines()]
    machines = [x for x in lines if x["phase"] == "machine"]
    measured_on = ("Measured on: " + "; ".join(f"{k}: {v}" for k, v in machines[0].items()
                                               if k != "phase") + "."
                   if machines else "Measured on: the machine the notes below name.")
    sections = [measured_on,
        f"## Menagerie robots (tests/robots) at {args.nbatch}x{args.nstep}", table(lines),
        "First batch: seconds from process start to the first batch in torch's hands, "
        "fresh processes, median of the warm runs; share: simloader's seconds after `import "
        "torch` less the raw script's. Steady state: simloader's steps/s over the raw "
        "engine's, same work, in one process on warm caches. JSON lines: "
        f"`{lines_path.name}`.", *args.note]
    title = "Menagerie robots on the GPU engines"
    if args.save and any(x["phase"] == "first" for x in lines):
        png = common.save_figure(args, "robots", plot(lines, title))
        sections.insert(3, f"![steps/s against the raw engine, first batches]({png.name})")
    if args.phase != "report":
        common.report(args, "robots", title, sections)
        return
    # rendered elsewhere than measured: the lines' machine, not this one's, heads the file
    print("\n\n".join(sections))
    if args.save:
        out = common.result_path(args, "robots", ".md")
        out.write_text(f"# {title}\n\n" + "\n\n".join(sections) + "\n")
        print(f"saved {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
