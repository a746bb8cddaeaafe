"""Episodes that end (`terminate=`) at the GPU engines' speed, one run.

Rows, per workload, measured in this process with alternating repetitions (medians):

- simloader, no rule: `SimDataset(control=Uniform())` iterated (the stream without episodes);
- simloader, with the rule: the same with `terminate=RULE` (dm_control's cart-pole names its
  pole joint `hinge_1`) (flags, autoreset inside the scan
  or the step graph);
- raw, same work: the raw loop `simloader bench` compares with (`RawMjx`, `RawWarp`);
- raw, same work + reset: that loop, plus after every step the rule on the state and the reset
  of the rows that met it to the model's initial state, in the plainest code a user would
  write: `jnp.where` over what a step reads inside the scan (MJX), torch `where` on MuJoCo
  Warp's arrays between graph replays (Warp), MuJoCo's kinematics first for a body rule.

The targets (issue #48): with a rule at least 0.95x the stream without one.

Run on the GPU machine from the repository root:
  python benchmarks/bench_episodes.py --model-dir .models/dm_control --save --results-dir $OUT
"""

from __future__ import annotations

import dataclasses

import torch

import common
from common import markdown_table

from simloader import terminate as T
from simloader import bench


@dataclasses.dataclass(frozen=True)
class Case:
    engine: str
    workload: bench.Workload
    rule: T.Rule

    def __str__(self) -> str:
        return f"{self.engine} {self.workload} {self.rule}"


CASES = [
    Case("warp", bench.Workload("humanoid", 8192, 200), T.Below("torso", 0.8)),
    Case("mjx", bench.Workload("cartpole", 8192, 1000), T.Outside("hinge_1", -0.2, 0.2)),
    Case("warp", bench.Workload("cartpole", 8192, 1000), T.Outside("hinge_1", -0.2, 0.2)),
]
QUICK = [
    Case("mjx", bench.Workload("cartpole", 256, 100), T.Outside("hinge_1", -0.2, 0.2)),
]


def rule_torch(rule, model, views):
    """(nworld,) bool: the raw Warp loop's rule on MuJoCo Warp's arrays now."""
    if isinstance(rule, T.Outside):
        q = views["qpos"][:, int(model.jnt_qposadr[model.joint(rule.joint).id])]
        return (q < rule.low) | (q > rule.high)
    xpos = views["xpos"].view(views["qpos"].shape[0], -1, 3)
    return xpos[:, model.body(rule.body).id, 2] < rule.height


def raw_warp_reset(model, w, seed, rule, sizes):
    """`RawWarp`, same work, plus the rule and the reset after every step: torch `where` on
    MuJoCo Warp's arrays between graph replays (a body rule's kinematics inside the graph,
    after the step)."""
    held = {}  # the data's views, the initial state, the flags: made at the first step

    def reset(raw, t):
        if not held:
            n = raw.w.nbatch
            held["views"] = {k: raw.wp.to_torch(getattr(raw.d, k)).reshape(n, -1) for k in
                             ("time", "qpos", "qvel", "act", "qacc_warmstart", "xpos")}
            # the state mj_resetData leaves: qpos0, all else zero
            held["x0"] = {k: torch.zeros_like(v[:1]) for k, v in held["views"].items()
                          if k != "xpos"}
            held["x0"]["qpos"][0] = torch.as_tensor(model.qpos0, device=raw.device)
            held["done"] = torch.empty((n, raw.w.nstep), dtype=torch.bool, device=raw.device)
        done = rule_torch(rule, model, held["views"])
        held["done"][:, t] = done
        for k, x0 in held["x0"].items():
            view = held["views"][k]
            view.copy_(torch.where(done[:, None], x0, view))

    return bench.RawWarp(model, w, seed, sizes=sizes, kinematics=isinstance(rule, T.Below),
                         after_step=reset)


def raw_mjx_reset(model, w, seed, rule):
    """`RawMjx`, same work, plus the rule and the reset inside the scan (`jnp.where` over
    what a step reads), after each step's state is recorded."""
    import jax
    import jax.numpy as jnp
    from simloader.backends.mjx.runtime import mjx

    kinematics = jax.vmap(mjx.kinematics, in_axes=(None, 0))
    start = mjx.make_data(mjx.put_model(model, impl="jax"), impl="jax")  # mj_resetData's
    adr = (int(model.jnt_qposadr[model.joint(rule.joint).id])
           if isinstance(rule, T.Outside) else None)
    body = model.body(rule.body).id if isinstance(rule, T.Below) else None

    def reset(mx, d):
        if adr is not None:
            done = (d.qpos[:, adr] < rule.low) | (d.qpos[:, adr] > rule.high)
        else:
            done = kinematics(mx, d).xpos[:, body, 2] < rule.height
        rows = lambda x: done.reshape((-1,) + (1,) * (x.ndim - 1))  # noqa: E731
        return d.replace(**{n: jnp.where(rows(getattr(d, n)), getattr(start, n),
                                         getattr(d, n)) for n in bench.STEP_READS}), \
            {"done": done}

    return bench.RawMjx(model, w, seed, after_step=reset)


def run_case(case: Case, args) -> tuple[list, dict]:
    model = common.load_model(case.workload.name, args.model_dir)
    w = case.workload
    plain = bench.SimloaderMeasure(model, w, case.engine, args.seed)
    ruled = bench.SimloaderMeasure(model, w, case.engine, args.seed, terminate=case.rule)
    options = ruled.ds.config.options
    raw = bench.raw_baseline(case.engine).matching(model, w, args.seed, options)
    if case.engine == "mjx":
        raw_reset = raw_mjx_reset(model, w, args.seed, case.rule)
    else:
        raw_reset = raw_warp_reset(model, w, args.seed, case.rule,
                                   sizes=(options.naconmax, options.njmax))
    nbatches = common.batches_for(args, max(raw.batch_s, raw_reset.batch_s))
    s = bench.interleave({
        "simloader, no rule": lambda: plain.measure(nbatches),
        "simloader, with the rule": lambda: ruled.measure(nbatches),
        "raw, same work": lambda: raw.measure(nbatches),
        "raw, same work + reset": lambda: raw_reset.measure(nbatches),
    }, args.repeats, desc=str(case))
    batch = next(iter(ruled.ds))
    episodes = int(batch["first"].sum()) + w.nbatch
    rows = [[case.engine, str(w), str(case.rule), name, bench.rate(1 / v)]
            for name, v in s.items()]
    ratios = {
        "with / without the rule (>= 0.95)": s["simloader, no rule"] / s["simloader, with the rule"],
        "with the rule / raw + reset": s["raw, same work + reset"] / s["simloader, with the rule"],
        "no rule / raw same work": s["raw, same work"] / s["simloader, no rule"],
        "episodes in one batch": episodes,
    }
    bench.drain()
    return rows, ratios


def main() -> None:
    p = common.parser(__doc__.split("\n")[0], [c.workload for c in CASES],
                      [c.workload for c in QUICK], throughput=True)
    p.add_argument("--cases", nargs="+", type=int,
                   help="indices of the default cases to run (default: all)")
    args = common.parse(p)
    cases = QUICK if args.quick else [CASES[i] for i in (args.cases or range(len(CASES)))]
    rows, summary = [], []
    for case in cases:
        case_rows, ratios = run_case(case, args)
        rows += case_rows
        summary.append([str(case)] + [bench.ratio(v) if not isinstance(v, int) else str(v)
                                      for v in ratios.values()])
        print(markdown_table(["engine", "workload", "rule", "loop", "steps/s"], rows), flush=True)
    headers = ["case", "with / without the rule (>= 0.95)", "with the rule / raw + reset",
               "no rule / raw same work", "episodes in one batch"]
    sections = [
        "Steps/s delivered (medians of alternating repetitions, one process):",
        markdown_table(["engine", "workload", "rule", "loop", "steps/s"], rows),
        "Ratios:", markdown_table(headers, summary)]
    common.report(args, "bench_episodes", "Episodes that end, at the GPU engines' speed",
                  sections)


if __name__ == "__main__":
    main()
