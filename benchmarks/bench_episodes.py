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
from simloader.tools import bench


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


class RawWarpReset(bench.RawWarp):
    """`RawWarp`, same work, plus the rule and the reset after every step (a body rule's
    kinematics inside the captured graph, after the step)."""

    def __init__(self, model, w, seed, rule, sizes):
        self.rule, self.model = rule, model
        super().__init__(model, w, seed, sizes=sizes)

    def _physics(self) -> None:
        self.mjw.step(self.m, self.d)
        if isinstance(self.rule, T.Below):
            self.mjw.kinematics(self.m, self.d)

    def __call__(self):
        wp, n = self.wp, self.w.nbatch
        if not hasattr(self, "views"):
            t = lambda a: wp.to_torch(a).reshape(n, -1)  # noqa: E731
            self.views = {k: t(getattr(self.d, k)) for k in
                          ("time", "qpos", "qvel", "act", "qacc_warmstart", "xpos")}
            self.x0 = {k: v[:1].clone() for k, v in self.views.items() if k != "xpos"}
            self.x0["time"].zero_()
            self.done = torch.empty((n, self.w.nstep), dtype=torch.bool, device=self.device)
        with torch.cuda.stream(self.stream):
            torch.rand(self.controls.shape, generator=self.gen, device=self.device,
                       out=self.controls)
            self.controls.mul_(self.high - self.low).add_(self.low)
            for t in range(self.w.nstep):
                self.ctrl.copy_(self.controls[:, t])
                wp.capture_launch(self.graph, stream=self.warp_stream)
                torch.cat(self.parts, dim=1, out=self.state[:, t])
                self.sensors[:, t] = self.sensordata
                done = rule_torch(self.rule, self.model, self.views)
                self.done[:, t] = done
                for k, x0 in self.x0.items():
                    view = self.views[k]
                    view.copy_(torch.where(done[:, None], x0, view))
        self.stream.synchronize()
        return {"state": self.state, "sensordata": self.sensors, "control": self.controls,
                "done": self.done}


def raw_mjx_reset(model, w, seed, rule):
    """`RawMjx`, same work, plus the rule and the reset inside the scan (`jnp.where`)."""
    import jax
    import jax.numpy as jnp
    from simloader.backends.mjx.runtime import mjx

    class RawMjxReset(bench.RawMjx):
        def __init__(self):
            self.w = w
            self.render = None
            self.mx = mjx.put_model(model, impl="jax")
            self.key = jax.random.key(seed)
            low, high = (jnp.asarray(b, jnp.float32) for b in bench.ctrl_bounds(model))
            step = jax.vmap(mjx.step, in_axes=(None, 0))
            kinematics = jax.vmap(mjx.kinematics, in_axes=(None, 0))
            nbatch, nstep, nu = w.nbatch, w.nstep, model.nu
            self.d0 = mjx.make_data(self.mx, impl="jax")
            adr = (int(model.jnt_qposadr[model.joint(rule.joint).id])
                   if isinstance(rule, T.Outside) else None)
            body = model.body(rule.body).id if isinstance(rule, T.Below) else None

            def batch(mx, d0, key, index):
                ctrl = jax.random.uniform(jax.random.fold_in(key, index), (nstep, nbatch, nu),
                                          minval=low, maxval=high)
                start = jax.tree.map(lambda x: jnp.broadcast_to(x, (nbatch, *x.shape)), d0)

                def body_fn(d, u):
                    d = step(mx, d.replace(ctrl=u))
                    if adr is not None:
                        done = (d.qpos[:, adr] < rule.low) | (d.qpos[:, adr] > rule.high)
                    else:
                        done = kinematics(mx, d).xpos[:, body, 2] < rule.height
                    state = jnp.concatenate([d.time[:, None], d.qpos, d.qvel, d.act], axis=1)
                    d = d.replace(**{n: jnp.where(
                        done.reshape((-1,) + (1,) * (getattr(d, n).ndim - 1)),
                        getattr(start, n), getattr(d, n)) for n in bench.STEP_READS})
                    return d, (state, d.sensordata, done)

                _, (state, sensordata, done) = jax.lax.scan(body_fn, start, ctrl)
                return {"state": state.swapaxes(0, 1), "sensordata": sensordata.swapaxes(0, 1),
                        "control": ctrl.swapaxes(0, 1), "done": done.swapaxes(0, 1)}

            import time
            t0 = time.perf_counter()
            with jax.default_matmul_precision("float32"):
                self.fn = jax.jit(batch).lower(self.mx, self.d0, self.key, 0).compile()
            self.compile_s = time.perf_counter() - t0
            self.index = 0
            self._time_first_batch()

    return RawMjxReset()


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
        raw_reset = RawWarpReset(model, w, args.seed, case.rule,
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
