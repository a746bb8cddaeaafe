"""Start-up: fresh processes to their first batch, simloader next to raw scripts, one run.

Every measurement is a fresh Python process (a "child") that does what a user's script does,
from interpreter start to the first batch in torch's hands, timed in phases:

- `startup`: the parent's `time.time()` at Popen to the child's first line (the interpreter);
- `import_torch`: `import torch` (first, as a torch user has it);
- `import_engine`: raw: JAX + `mujoco.mjx` / `warp` + `mujoco_warp` / `mujoco` + rollout;
  simloader: `import simloader`;
- `construct`: raw: load the model, put it on the device, make the data; simloader:
  `SimDataset(...)`;
- `trace`, `compile`: raw JAX: `jax.jit(f).trace(...)` + `.lower()`, and `.compile()` (JAX's
  persistent compilation cache on); raw Warp: the graph capture of one `mjw.step`, and the
  eager step before it (which builds or loads Warp's kernels); simloader: `stats["trace_s"]`
  and `stats["compile_s"]` ("-" where simloader does not report them);
- `first_sim`: the first batch simulated until ready (simloader: the rest of `next(iter(ds))`);
- `handoff`: raw: to torch (`torch.from_dlpack`, `wp.to_torch`, `torch.from_numpy`);
  simloader: waiting on torch's stream;
- `total`: process start to the first batch in torch's hands; `after torch`: the same from
  the end of `import torch`; `wall`: the parent's wall clock of the whole process (exit
  included).

Cold and warm: each (engine, workload, raw or simloader) gets a cache root of its own
(`XDG_CACHE_HOME`, `JAX_COMPILATION_CACHE_DIR`, `WARP_CACHE_PATH`, `CUDA_CACHE_PATH` under it),
empty for the cold run, then reused for `--repeats` warm runs (median, min-max). Raw and
simloader alternate in the warm runs. "Cold" means cold compilation caches: the OS page cache is
not dropped (the libraries' files are read from memory after the first child).

The raw scripts import neither simloader nor this folder; they are the recipes of
`simloader.bench` (`RawMjx`, `RawWarp`, `raw_rollout`), written out (`simloader.bench.startup`).
`XLA_PYTHON_CLIENT_PREALLOCATE=false` is set for both (simloader's default) unless already set.

Run on the GPU machine from the repository root:
  python benchmarks/bench_startup.py --model-dir .models/dm_control --save --results-dir $OUT
Smoke run on a laptop:
  python benchmarks/bench_startup.py --quick --engines cpu mjx
Where a warm first batch spends its seconds, both sides (sampled stacks of every thread):
  python benchmarks/bench_startup.py --workloads warp:humanoid:8192x200 --profile $OUT/prof
"""

from __future__ import annotations

import argparse
import pathlib
import shutil
import statistics
import sys
import tempfile
from typing import Optional

import common
from simloader.bench.startup import (CPU_AFTER_TORCH_S, PHASES, RAW_SCRIPT, SIM_OPTIONS,
                                     SIMLOADER, profile_table, run_child)

ENGINES = ("cpu", "mjx", "warp")
DEFAULT = ["mjx:cartpole:4096x200", "mjx:humanoid:4096x200", "warp:humanoid:8192x200",
           "cpu:cartpole:4096x200"]
QUICK = ["cpu:cartpole:64x20", "mjx:cartpole:64x20", "warp:cartpole:64x20"]

# -- the parent ---------------------------------------------------------------------------------

def parse_workload(text: str) -> tuple[str, common.Workload]:
    """`mjx:humanoid:4096x200` -> ("mjx", Workload("humanoid", 4096, 200))."""
    try:
        engine, rest = text.split(":", 1)
    except ValueError:
        engine, rest = "", ""
    if engine not in ENGINES:
        raise argparse.ArgumentTypeError(
            f"expected ENGINE:MODEL:NBATCHxNSTEP with ENGINE one of {', '.join(ENGINES)}, "
            f"such as jax:humanoid:4096x200, got {text!r}")
    return engine, common.parse_workload(rest)


def model_path(name: str, folder: Optional[pathlib.Path]) -> str:
    """`<model dir>/<name>.xml` (as the other benchmarks), else simloader's built-in model."""
    if folder is not None or any(d.is_dir() for d in common.MODEL_DIRS):
        path = common.model_dir(folder) / f"{name}.xml"
        if path.is_file():
            return str(path.resolve())  # the children run in their cache folder
        if folder is not None:
            raise SystemExit(f"model {name!r}: no file {path}")
    from simloader import models
    return str(models.builtin_path(name))


def fmt(values: list[Optional[float]], spread: bool = False) -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return "-"
    med = statistics.median(vals)
    if spread and len(vals) > 1:
        return f"{med:.2f} ({min(vals):.2f}-{max(vals):.2f})"
    return f"{med:.2f}"


def median(values: list[Optional[float]]) -> Optional[float]:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


def target(engine: str, model: str, kind: str) -> tuple[str, Optional[float]]:
    """(what, bound) of the issue's targets for simloader's `kind` ("cold"/"warm") row."""
    if engine == "cpu":
        return "after torch", CPU_AFTER_TORCH_S
    if kind == "cold":
        return "ratio", 1.05
    if engine == "warp":
        return "ratio", 1.05
    return "ratio", 0.75 if model == "humanoid" else 0.9


def table(engine: str, w: common.Workload, runs: dict[tuple[str, str], list[dict]]) -> str:
    headers = ["run", *PHASES, "total", "after torch", "wall", "traces/compiles/loaded",
               "ratio sim/raw", "target"]
    rows = []
    for kind in ("cold", "warm"):
        for who in ("raw", "simloader"):
            got = runs.get((who, kind), [])
            ok = [r for r in got if "error" not in r]
            label = f"{who} {kind}" + (f" (n={len(ok)})" if kind == "warm" else "")
            if not ok:
                rows.append([label, *["-"] * (len(headers) - 2),
                             "FAILED" if got else "-"])
                continue
            phases = [fmt([r["phases"].get(p) for r in ok]) for p in PHASES]
            total = median([r["total"] for r in ok])
            after = median([r["after_torch"] for r in ok])
            counts = "-"
            if who == "simloader":
                x = ok[-1]["extra"]
                counts = "/".join("-" if x.get(k) is None else str(x[k])
                                  for k in ("traces", "compiles", "programs_loaded"))
            ratio_s, target_s = "", ""
            if who == "simloader":
                raw = [r for r in runs.get(("raw", kind), []) if "error" not in r]
                raw_total = median([r["total"] for r in raw])
                ratio = total / raw_total if raw_total else None
                ratio_s = "-" if ratio is None else f"{ratio:.2f}x"
                what, bound = target(engine, w.name, kind)
                value = after if what == "after torch" else ratio
                if bound is not None and value is not None:
                    unit = " s after torch" if what == "after torch" else "x"
                    target_s = (f"<= {bound}{unit}: "
                                f"{'PASS' if value <= bound else 'MISS'}")
            rows.append([label, *phases, fmt([r["total"] for r in ok], spread=True),
                         fmt([r["after_torch"] for r in ok], spread=True),
                         fmt([r["wall"] for r in ok]), counts, ratio_s, target_s])
    title = f"## {engine}: {w} (seconds from the process start; warm: median (min-max))"
    return title + "\n\n" + common.markdown_table(headers, rows)


def failures(engine: str, w: common.Workload, runs: dict) -> list[str]:
    out = []
    for (who, kind), got in runs.items():
        for i, r in enumerate(got):
            if "error" in r:
                out.append(f"{engine} {w} {who} {kind} #{i}: {r['error'].strip()[-1500:]}")
    return out


def plot(args: argparse.Namespace, results: list) -> None:
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot", file=sys.stderr)
        return
    if not results:
        return
    fig, axes = plt.subplots(len(results), 1, figsize=(9, 2.2 * len(results) + 0.8),
                             squeeze=False)
    colors = plt.get_cmap("tab10").colors
    for ax, (engine, w, runs) in zip(axes[:, 0], results):
        labels, lefts = [], []
        for y, (who, kind) in enumerate([(w_, k) for k in ("cold", "warm")
                                         for w_ in ("raw", "simloader")]):
            ok = [r for r in runs.get((who, kind), []) if "error" not in r]
            labels.append(f"{who} {kind}")
            left = 0.0
            for i, p in enumerate(PHASES):
                v = median([r["phases"].get(p) for r in ok]) or 0.0
                ax.barh(y, v, left=left, color=colors[i % 10],
                        label=p if y == 0 else None)
                left += v
            lefts.append(left)
        ax.set_yticks(range(len(labels)), labels)
        ax.invert_yaxis()
        ax.set_title(f"{engine}: {w}", fontsize=10)
        ax.set_xlabel("seconds from process start to the first batch")
    axes[0, 0].legend(fontsize=7, ncol=len(PHASES), loc="lower left", bbox_to_anchor=(0, 1.15))
    fig.tight_layout()
    path = common.result_path(args, "bench_startup", ".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    print(f"saved {path}", file=sys.stderr)


def save(args: argparse.Namespace, sections: list[str]) -> None:
    env = common.environment()
    env["warp"] = (f"warp-lang {common._version('warp-lang')}, mujoco-warp "
                   f"{common._version('mujoco-warp')}")
    command = env.pop("command")
    env["command"] = command
    lines = ["# Start-up: fresh processes to the first batch, simloader and raw", ""]
    lines += [f"- {k}: `{v}`" if k == "command" else f"- {k}: {v}" for k, v in env.items()]
    path = common.result_path(args, "bench_startup", ".md")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n\n" + "\n\n".join(sections) + "\n")
    print(f"saved {path}", file=sys.stderr)


def write_profiles(path: pathlib.Path, profiles: list[tuple[str, pathlib.Path, dict]]) -> None:
    """profiles.md: per profiled child, its seconds after torch and where they went."""
    parts = ["# Where the warm first batches spend their seconds", (
        "Children of their own, after the timed ones and kept out of their figures (the "
        "sampling slows them): each child's threads sampled every few milliseconds from the "
        "end of `import torch` to the first batch (`simloader.bench.startup.PRELUDE`), each "
        "sample weighted by the time since the last; inclusive: the seconds of the stacks "
        "the frame is on; threads blocked in a wait count too. Compare the sides' frames.")]
    for title, folded, line in profiles:
        parts += [f"## {title}: {line['after_torch']:.2f} s after torch",
                  profile_table(folded, line["extra"]["profile"]["unit_s"])]
    path.write_text("\n\n".join(parts) + "\n")
    print(f"profiles: {path}", file=sys.stderr)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help=f"tiny sizes for a smoke run on a laptop ({' '.join(QUICK)})")
    p.add_argument("--workloads", nargs="+", type=parse_workload,
                   metavar="ENGINE:MODEL:NBATCHxNSTEP",
                   help=f"what to run (default: {' '.join(DEFAULT)})")
    p.add_argument("--engines", nargs="+", choices=ENGINES, default=list(ENGINES),
                   help="engines to run (filters the workloads)")
    p.add_argument("--model-dir", type=pathlib.Path,
                   help=f"folder of the MJCF files (default: the first of "
                        f"{', '.join(str(d) for d in common.MODEL_DIRS)} that exists, else "
                        f"simloader's built-in models)")
    p.add_argument("--repeats", type=int, default=2, help="warm runs of each child")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=600.0, help="seconds per child")
    p.add_argument("--cache-root", type=pathlib.Path,
                   help="folder for the children's caches (default: a fresh temporary folder, "
                        "removed at the end)")
    p.add_argument("--keep-caches", action="store_true", help="leave the caches in place")
    p.add_argument("--profile", type=pathlib.Path,
                   help="also run --repeats profiled warm children per side, after the timed "
                        "ones and kept out of their figures (sampling slows them), writing "
                        "their sampled stacks here (every thread's, from the end of `import "
                        "torch` to the first batch; folded, one file a child) and "
                        "profiles.md, the frames where each spent its seconds")
    common.add_output_options(p)
    args = p.parse_args()
    if args.profile is not None:  # the children run in their cache folders
        args.profile = args.profile.resolve()

    chosen = args.workloads or [parse_workload(t) for t in (QUICK if args.quick else DEFAULT)]
    chosen = [(e, w) for e, w in chosen if e in args.engines]
    import torch
    notes = []
    if any(e == "warp" for e, _ in chosen) and not torch.cuda.is_available():
        notes.append("warp rows skipped: no CUDA GPU (Warp on the CPU is not the target)")
        chosen = [(e, w) for e, w in chosen if e != "warp"]
    for n in notes:
        print(n, file=sys.stderr)

    root = args.cache_root or pathlib.Path(tempfile.mkdtemp(prefix="bench_startup-"))
    root.mkdir(parents=True, exist_ok=True)
    plan = []  # (engine, workload, who, kind, child root, script, spec)
    for engine, w in chosen:
        spec = {"model": model_path(w.name, args.model_dir), "nbatch": w.nbatch,
                "nstep": w.nstep, "seed": args.seed, **SIM_OPTIONS[engine]}
        roots = {}
        for who in ("raw", "simloader"):
            roots[who] = root / f"{engine}-{w.name}-{w.nbatch}x{w.nstep}-{who}"
            shutil.rmtree(roots[who], ignore_errors=True)  # cold for real
            roots[who].mkdir(parents=True)
        order = [("raw", "cold"), ("simloader", "cold")]
        for kind in ("warm", "profiled") if args.profile is not None else ("warm",):
            for rep in range(args.repeats):
                pair = [("raw", kind), ("simloader", kind)]
                order += pair if rep % 2 else pair[::-1]
        for who, kind in order:
            s = dict(spec, jax_cache=str(roots[who] / "jax"))
            script = SIMLOADER if who == "simloader" else RAW_SCRIPT[engine]
            plan.append((engine, w, who, kind, roots[who], script, s))

    results: dict[tuple[str, str], dict] = {}
    profiles: list[tuple[str, pathlib.Path, dict]] = []  # (title, folded file, its line)
    if args.profile is not None:
        args.profile.mkdir(parents=True, exist_ok=True)
    try:
        for i, (engine, w, who, kind, croot, script, spec) in enumerate(
                common.progress(plan, desc="children")):
            folded = (args.profile / f"{engine}-{w.name}-{w.nbatch}x{w.nstep}-{who}-{i}.folded"
                      if kind == "profiled" else None)
            r = run_child(script, croot, spec, who == "simloader", args.timeout,
                          profile=folded)
            if folded is not None:  # not the benchmark's figures
                if "error" not in r:
                    profiles.append((f"{engine} {w} {who}, child {i}", folded, r))
                continue
            results.setdefault((engine, str(w)), {"engine": engine, "w": w, "runs": {}})[
                "runs"].setdefault((who, kind), []).append(r)
    finally:
        if not args.keep_caches:
            shutil.rmtree(root, ignore_errors=True)

    if profiles:
        write_profiles(args.profile / "profiles.md", profiles)
    sections, errors = [], []
    for entry in results.values():
        sections.append(table(entry["engine"], entry["w"], entry["runs"]))
        errors += failures(entry["engine"], entry["w"], entry["runs"])
    sections.append(
        "Phases in seconds: startup (interpreter), import_torch, import_engine (raw: the "
        "engine; simloader: `import simloader`), construct (model on the device, data / "
        "`SimDataset(...)`), trace and compile (raw JAX: `.trace().lower()` and `.compile()`; "
        "raw Warp: graph capture and the eager step that builds the kernels; simloader: "
        "`stats['trace_s']`, `stats['compile_s']`), first_sim (simloader: the rest of "
        "`next(iter(ds))`), handoff (to torch). total: process start to the first batch in "
        "torch's hands; after torch: from the end of `import torch`; wall: the whole process "
        "as the parent saw it. Cold: empty cache roots (XDG_CACHE_HOME, "
        "JAX_COMPILATION_CACHE_DIR, WARP_CACHE_PATH, CUDA_CACHE_PATH), one per engine, "
        "workload and raw/simloader; warm: the same roots again. traces/compiles/loaded: "
        "simloader's `stats` after the first batch. Phases are not matched one to one: "
        "`import simloader` does not import JAX or Warp, so simloader's construct includes "
        "them, and simloader's compile includes its tracing where it reports no `trace_s`; "
        "compare totals.")
    if notes:
        sections.append("\n".join(f"Note: {n}." for n in notes))
    if errors:
        sections.append("Failures:\n\n```\n" + "\n\n".join(errors) + "\n```")
    print("\n\n".join(sections))
    if args.save:
        save(args, sections)
        plot(args, [(e["engine"], e["w"], e["runs"]) for e in results.values()])


if __name__ == "__main__":
    main()
