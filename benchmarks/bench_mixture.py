"""A `simloader.Mixture` against its members alone: throughput and compilations.

For each member (`--members MODEL:NBATCHxNSTEP ...`, all on `--backend`), measured in this
process with alternating repetitions (medians):

- alone: a fresh iterator of the member's `SimDataset`, warmed up (`--warmup` batches), then
  `--batches` batches timed, `common.sync()` after each: seconds per batch, steps/s;
- in the mixture: a fresh iterator of `Mixture(members, weights)` over another set of the same
  members (own datasets: their engines compile and capture on their own), warmed up until every
  member has delivered `--warmup` batches, then `--batches` x the number of members batches
  timed the same way, each batch's task recorded.

The mixture's ratio is its throughput over the members' time-weighted throughput alone: the
steps of the mixture's timed batches over the sum, over those batches, of the member's alone
time per batch (with `--pad`, each batch's draws: rows of a task / that member's nbatch).
Target: >= 0.9x. Each member's iterator lives for the whole mixture run, so switching
between members must not recompile: the compilations (MJX: `compiles`, a program traced or
loaded; `traces`, `programs_loaded` for information) and graph captures (Warp:
`graph_captures`) each member's engine counted alone and in the mixture must be equal (one
each). The CPU engine compiles nothing.

Run on the GPU machine from the repository root:
  python benchmarks/bench_mixture.py --backend warp --members cartpole:8192x200 \\
      humanoid:4096x100 --save --results-dir $OUT
  python benchmarks/bench_mixture.py --quick             # a smoke run on a laptop's CPU
"""

from __future__ import annotations

import argparse
import pathlib
import statistics
import time

import torch

import common
from common import markdown_table

import simloader
from simloader import controls
from simloader import bench

MEMBERS = [bench.Workload("cartpole", 8192, 200), bench.Workload("humanoid", 4096, 100)]
QUICK = [bench.Workload("cartpole", 64, 50), bench.Workload("humanoid", 16, 20)]
# the engines' own counters of compilations and graph captures (their entry.py's `counters`)
COMPILED = ("compiles", "graph_captures")
INFO = ("traces", "programs_loaded")


def model_for(name: str, args: argparse.Namespace):
    """A model name simloader knows (built-in, Gymnasium's), or `<model-dir>/<name>.xml`
    (dm_control's, as the other benchmarks load them) when --model-dir is given or the name
    is not one of simloader's."""
    if args.model_dir is None and name in simloader.named_models():
        return name
    return common.load_model(name, args.model_dir)


def make_member(w: bench.Workload, args: argparse.Namespace, seed: int) -> simloader.SimDataset:
    return simloader.SimDataset(model_for(w.name, args), backend=args.backend, nbatch=w.nbatch,
                                nstep=w.nstep, seed=seed, control=controls.Uniform(),
                                nthread=args.nthread)


def counts(ds: simloader.SimDataset) -> dict[str, int]:
    stats = ds.stats
    return {k: int(stats[k]) for k in COMPILED + INFO if k in stats}


def time_alone(ds: simloader.SimDataset, warmup: int, nbatches: int) -> float:
    """Seconds per batch of a fresh iterator of `ds`, after `warmup` batches."""
    it = iter(ds)
    try:
        for _ in range(warmup):
            next(it)
            common.sync()
        start = time.perf_counter()
        for _ in range(nbatches):
            next(it)
            common.sync()
        return (time.perf_counter() - start) / nbatches
    finally:
        it.close()
        bench.drain()


def draws_of(batch: dict, nbatch: list[int]) -> list[int]:
    """The members drawn for one mixture batch (each as often as drawn)."""
    task = batch["task"]
    if task.dim() == 0:
        return [int(task)]
    out = []
    for i, rows in enumerate(torch.bincount(task, minlength=len(nbatch)).tolist()):
        out += [i] * (rows // nbatch[i])
    return out


def time_mixture(mixture: simloader.Mixture, warmup: int, nbatches: int,
                 nbatch: list[int]) -> tuple[float, list[int]]:
    """(seconds, the members drawn) of `nbatches` batches of a fresh iterator of the mixture,
    after every member of weight > 0 has delivered `warmup` batches."""
    it = iter(mixture)
    try:
        delivered = [0] * len(nbatch)
        needed = [warmup if w > 0 else 0 for w in mixture.weights]
        for _ in range(1000 * max(1, warmup)):
            if all(d >= n for d, n in zip(delivered, needed)):
                break
            for i in draws_of(next(it), nbatch):
                delivered[i] += 1
            common.sync()
        drawn = []
        start = time.perf_counter()
        for _ in range(nbatches):
            batch = next(it)
            common.sync()
            drawn += draws_of(batch, nbatch)
        return time.perf_counter() - start, drawn
    finally:
        it.close()
        bench.drain()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help=f"tiny sizes on the CPU engine ({' '.join(map(str, QUICK))})")
    p.add_argument("--backend", default=None, choices=("cpu", "mjx", "warp", "auto"),
                   help="engine of every member (default: auto, --quick: cpu)")
    p.add_argument("--members", nargs="+", type=common.parse_workload,
                   metavar="MODEL:NBATCHxNSTEP",
                   help=f"the members (default: {' '.join(map(str, MEMBERS))})")
    p.add_argument("--weights", nargs="+", type=float,
                   help="the mixture's weights, one per member (default: equal)")
    p.add_argument("--pad", action="store_true",
                   help="Mixture(pad=True): rows of every draw in each batch (the members' "
                        "nstep must agree)")
    p.add_argument("--batches", type=int,
                   help="timed batches of each member alone; the mixture times this many "
                        "per member (default 10, --quick 3)")
    p.add_argument("--warmup", type=int, default=2,
                   help="batches before timing (the mixture: of every member)")
    p.add_argument("--repeats", type=int, help="alternating repetitions (default 3, --quick 2)")
    p.add_argument("--nthread", type=int,
                   help="CPU engine threads per member (default: simloader's; on a small "
                        "machine lower it, every running member has its own)")
    p.add_argument("--model-dir", type=pathlib.Path,
                   help="load MODEL from <dir>/MODEL.xml (dm_control's models) instead of "
                        "simloader's named models")
    p.add_argument("--seed", type=int, default=0)
    common.add_output_options(p)
    args = p.parse_args()
    members = args.members or (QUICK if args.quick else MEMBERS)
    args.backend = args.backend or ("cpu" if args.quick else "auto")
    args.batches = args.batches or (3 if args.quick else 10)
    args.repeats = args.repeats or (2 if args.quick else 3)
    names = [str(w) for w in members]
    if len(set(names)) < len(names):  # the same workload twice: numbered
        names = [f"{i}:{w}" for i, w in enumerate(members)]
    nbatch = [w.nbatch for w in members]

    alone = [make_member(w, args, args.seed + i) for i, w in enumerate(members)]
    mixed = [make_member(w, args, args.seed + i) for i, w in enumerate(members)]
    mixture = simloader.Mixture(dict(zip(names, mixed)), weights=args.weights,
                                seed=args.seed, pad=args.pad)
    backends = [ds.config.backend for ds in alone]

    # alternating repetitions, the order reversed every other one
    alone_s: list[list[float]] = [[] for _ in members]
    mixture_runs: list[tuple[float, list[int]]] = []
    measures = [(i, lambda i=i: alone_s[i].append(
        time_alone(alone[i], args.warmup, args.batches))) for i in range(len(members))]
    measures.append(("mixture", lambda: mixture_runs.append(time_mixture(
        mixture, args.warmup, args.batches * len(members), nbatch))))
    for rep in common.progress(range(args.repeats), desc="repetitions"):
        for _, measure in (measures if rep % 2 == 0 else measures[::-1]):
            measure()

    batch_s = [statistics.median(s) for s in alone_s]
    rows = [[names[i], backends[i], f"{batch_s[i] * 1e3:,.1f}",
             bench.rate(members[i].steps / batch_s[i])] for i in range(len(members))]
    ratios, rates = [], []
    for elapsed, drawn in mixture_runs:
        steps = sum(members[i].steps for i in drawn)
        weighted_alone_s = sum(batch_s[i] for i in drawn)  # the same batches, each alone
        ratios.append(weighted_alone_s / elapsed)
        rates.append((steps / elapsed, steps / weighted_alone_s))
    ratio = statistics.median(ratios)
    mixture_rate, alone_rate = rates[ratios.index(sorted(ratios)[len(ratios) // 2])]
    shares = [sum(d == i for _, drawn in mixture_runs for d in drawn) for i in
              range(len(members))]
    total = sum(shares)
    rows.append(["mixture (" + ", ".join(f"{n} {s / total:.0%}" for n, s in
                                         zip(names, shares)) + ")",
                 "/".join(sorted(set(backends))), "-", bench.rate(mixture_rate)])

    compiled_rows, equal = [], True
    for name, a, m in zip(names, alone, mixed):
        ca, cm = counts(a), counts(m)
        same = all(ca.get(k) == cm.get(k) for k in COMPILED)
        equal &= same
        fmt = lambda c: ", ".join(f"{k} {v}" for k, v in c.items()) or "none (CPU engine)"  # noqa: E731
        compiled_rows.append([name, fmt(ca), fmt(cm), "yes" if same else "NO"])

    summary = [[f"{ratio:.3f}", bench.rate(mixture_rate), bench.rate(alone_rate),
                "yes" if ratio >= 0.9 else "NO", "yes" if equal else "NO"]]
    sections = [
        f"Steps/s delivered ({args.repeats} alternating repetitions, medians; alone: "
        f"{args.batches} timed batches per member, mixture: {args.batches * len(members)} "
        f"batches{', pad=True' if args.pad else ''}, weights "
        f"{[round(float(w), 3) for w in mixture.weights]}):",
        markdown_table(["member", "engine", "ms per batch alone", "steps/s"], rows),
        "The mixture against its members alone (time-weighted: the same batches, each at its "
        "member's alone speed):",
        markdown_table(["mixture / members alone (>= 0.9)", "mixture steps/s",
                        "time-weighted alone steps/s", ">= 0.9x", "compilations equal"],
                       summary),
        "Compilations and graph captures, each member's engine over all its runs:",
        markdown_table(["member", "alone", "in the mixture", "equal"], compiled_rows),
    ]
    common.report(args, "bench_mixture", "A Mixture against its members alone", sections)


if __name__ == "__main__":
    main()
