"""Scale-out: every engine under torchrun, one process per GPU, throughput against one GPU.

For each engine (`cpu`: MuJoCo on the CPU; `mjx`: MJX on JAX; `warp`: MuJoCo Warp), mode and
number of ranks of `--nprocs`, one `torchrun --standalone --nproc_per_node=N` job of this script
in its child role: each rank streams its own part of one seeded stream on its own GPU
(`cuda:LOCAL_RANK`; the CPU without one) and times `--batches` batches after a warm-up batch.
With `--nodes M` (M > 1) the job is M local "nodes" at once: M torchrun processes with the
static rendezvous (`--nnodes M --node-rank i --master-addr 127.0.0.1 --master-port PORT`,
N/M ranks each), node i seeing GPUs i*N/M .. (i+1)*N/M-1 only (`CUDA_VISIBLE_DEVICES`), so
LOCAL_RANK restarts at 0 in every node while the global ranks stay distinct: "2 nodes of 2
GPUs" on a 4-GPU host. The modes:

- `open`: open-loop uniform controls, state and sensors of every step;
- `camera`: the same with a 64x64 RGB camera;
- `policy`: a torch MLP (2x256) on the rank's device chooses every step's controls;
- `write`: every rank writes its slots of one store (`simloader.write`), timed until written;
- `ddp`: the DDP world-model example (`examples/train_world_model_ddp.py`), training included
  (engines `cpu` and `mjx`: the example chooses its MJX implementation itself).

A row reports the steps/s of all ranks together (all ranks' steps over the slowest rank's
time), per rank, and against the first `--nprocs` in the same run; and two checks of the
stream: every rank's first batch differs from every other's (seeds by global rank), and what
simulating that batch again from (seed, rank, batch index) gives: "bit-equal" (torch.equal on
every key), else whether the draws are equal (initial_state and control bit for bit) and the
largest |difference| of "state" over the ranks ("draws equal; states apart by 2.1e+01").
`--deterministic` builds every dataset with `deterministic=True` (bit-identical batches for a
seed where the engine can); an engine that cannot refuses, as does any combination an engine
refuses (a camera on MJX-JAX, say): a row saying so.

Targets (issue: several GPUs): 2 GPUs at least 1.95x one for Warp humanoid 8192 per GPU and
JAX cart-pole; 4 GPUs at least 3.8x. NVLink multicast stays off in NCCL (shared machines).

    python benchmarks/scale_out.py --nprocs 1 2 --save --results-dir $OUT        # on 2 GPUs
    python benchmarks/scale_out.py --nprocs 2 4 --nodes 2 --save --results-dir $OUT  # 4 GPUs
    python benchmarks/scale_out.py --nprocs 1 2 --deterministic --modes open policy \\
        --tag deterministic --save --results-dir $OUT
    python benchmarks/scale_out.py --quick --engines cpu --nprocs 1 2         # CPU smoke run
    python benchmarks/scale_out.py --quick --engines cpu --nprocs 2 --nodes 2  # 2 CPU "nodes"
    # one node against two, interleaved three times: a closed loop's rate moves from job to
    # job (Python dispatches every step), so one job against one cannot resolve 5%
    python benchmarks/scale_out.py --engines mjx --modes policy --nprocs 4 --nodes 1 2 \
        --repeats 3 --batches 20 --save --results-dir $OUT
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time

import common

from simloader.bench.ranks import NCCL_SAFE_ENV

EXAMPLE = common.REPO / "examples" / "train_world_model_ddp.py"
ENGINES = {"cpu": {"backend": "cpu"}, "mjx": {"backend": "mjx"}, "warp": {"backend": "warp"}}
MODES = ("open", "camera", "policy", "write", "ddp")
WORKLOADS = {"cpu": "cartpole:1024x100", "mjx": "cartpole:8192x1000",
             "warp": "humanoid:8192x200"}
QUICK = {"cpu": "cartpole:64x20", "mjx": "cartpole:64x20", "warp": "cartpole:64x20"}
QUICK_CAMERA = "cartpole:4x5"  # a CPU without a GPU renders about 30 frames/s
REFUSED = 3  # the child's exit status when the engine refuses the combination


# --------------------------------------------------------------------------- one rank

def _dataset(args, device):
    import torch
    import simloader
    w = common.parse_workload(args.workload)
    record = ["state", "sensordata"]
    if args.mode == "camera":
        # the model's first camera (MuJoCo Warp renders the model's cameras, not the free one)
        camera = 0 if simloader.load_model(w.name).ncam else -1
        record.append(simloader.Camera(camera, height=64, width=64))
    drive = {"control": simloader.controls.Uniform()}
    if args.mode == "policy":
        import mujoco
        model = simloader.load_model(w.name)
        nstate = mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)  # "state"
        mlp = torch.nn.Sequential(torch.nn.Linear(nstate, 256), torch.nn.Tanh(),
                                  torch.nn.Linear(256, 256), torch.nn.Tanh(),
                                  torch.nn.Linear(256, model.nu))
        dtype = torch.float64 if args.engine == "cpu" else torch.float32
        mlp = mlp.to(device=device, dtype=dtype)
        drive = {"policy": lambda obs: mlp(obs["state"])}
    extra = {"deterministic": True} if args.deterministic else {}
    return simloader.SimDataset(w.name, nbatch=w.nbatch, nstep=w.nstep, seed=args.seed,
                                record=tuple(record), device=device, **drive, **extra,
                                **ENGINES[args.engine])


def _digest(batch) -> str:
    h = hashlib.sha256()
    for key in ("initial_state", "control"):
        h.update(batch[key].detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def _again(ds, shard, index, batch) -> dict:
    """The rank's batch `index` simulated again from its seed, against `batch`: `draws`
    (initial_state and control bit-equal), `bit` (torch.equal on every key), `apart` (the
    largest |difference| of "state") and `differ` (the keys not bit-equal)."""
    import torch
    backend = ds.make_backend(shard)
    try:
        _, again, _ = next(iter(ds.stream(backend, [index])))
    finally:
        backend.close()
    from simloader import streams
    from simloader.batch import flat
    # the stream keys name the delivering iterator's streams (`stream()` adds none)
    a, b = flat(again), {k: v for k, v in flat(batch).items() if k not in streams.KEYS}
    differ = sorted(k for k in set(a) | set(b)
                    if k not in a or k not in b or not torch.equal(a[k], b[k]))
    apart = 0.0
    if "state" in differ and a["state"].shape == b["state"].shape:
        apart = (a["state"].double() - b["state"].double()).abs().max().item()
    return {"draws": not {"initial_state", "control"} & set(differ), "bit": not differ,
            "apart": apart, "differ": differ}


def _again_text(checks) -> str:
    """What the ranks' batches simulated again say: "bit-equal", or "draws equal; states apart
    by 2.1e+01" (the largest over the ranks)."""
    if all(c["bit"] for c in checks):
        return "bit-equal"
    draws = "draws equal" if all(c["draws"] for c in checks) else "draws DIFFER"
    apart = max(c["apart"] for c in checks)
    differ = sorted({k for c in checks for k in c["differ"]} - {"initial_state", "control"})
    if apart != apart or apart > 0:  # NaN counts as apart
        return f"{draws}; states apart by {apart:.1e}"
    if "state" in differ:
        return f"{draws}; state not comparable"
    return f"{draws}; states bit-equal; {', '.join(differ) or 'nothing else'} differ"


def child(args) -> None:
    """One rank of a torchrun job: its throughput and stream checks, gathered by rank 0."""
    import torch
    import torch.distributed as dist
    import simloader
    from simloader import sharding
    gpu = torch.cuda.is_available()
    # under --nodes, cuda:LOCAL_RANK is right: this node's CUDA_VISIBLE_DEVICES are its GPUs
    local = int(os.environ.get("LOCAL_RANK", "0"))
    device = f"cuda:{local}" if gpu else "cpu"
    if gpu:
        torch.cuda.set_device(local)
    dist.init_process_group("nccl" if gpu else "gloo")
    rank, world = dist.get_rank(), dist.get_world_size()
    try:
        ds = _dataset(args, device)
    except (ValueError, TypeError) as e:  # the engine refuses this combination
        if rank == 0:
            with open(args.json, "w") as f:
                json.dump({"refused": str(e).splitlines()[0][:160]}, f)
        dist.destroy_process_group()
        raise SystemExit(REFUSED)
    w = ds.config
    shard = sharding.current_shard()
    it = iter(ds)
    first = next(it)  # warm-up: compilation, graph capture, threads
    digest = _digest(first)
    dist.barrier()
    start = time.perf_counter()
    if args.mode == "write":
        it.close()
        simloader.write(ds, args.store, batches=args.batches * world, progress=False)
    else:
        for _ in range(args.batches):
            next(it)
            if gpu:
                torch.cuda.current_stream().synchronize()
        it.close()
    seconds = time.perf_counter() - start
    # checked after the timed window: simulating batch 0 again before it let the batches
    # queued behind the warm-up one finish untimed, which inflated short windows (MJX's
    # cart-pole read 52.8M steps/s over 8 batches against 34.4M over 40, 2026-11-26)
    same = _again(ds, shard, 0, first)
    results = [None] * world
    dist.all_gather_object(results, {"rank": rank, "seconds": seconds, "digest": digest,
                                     "again": same, "device": str(device),
                                     "node": int(os.environ.get("GROUP_RANK", "0")),
                                     "gpus": os.environ.get("CUDA_VISIBLE_DEVICES", "")})
    if rank == 0:
        steps = args.batches * w.nbatch * w.nstep
        slowest = max(r["seconds"] for r in results)
        out = {"steps_per_s": world * steps / slowest,
               "per_rank": [steps / r["seconds"] for r in results],
               "distinct": len({r["digest"] for r in results}) == world,
               "again": _again_text([r["again"] for r in results]),
               "placement": [[r["node"], r["device"], r["gpus"]] for r in results],
               "device": torch.cuda.get_device_name(0) if gpu else "CPU"}
        if args.mode == "write":
            stored = simloader.StoredDataset(args.store)
            out["stored"] = len(stored)
            out["ranks_in_store"] = sorted({stored.provenance(i)["rank"]
                                            for i in range(0, len(stored), w.nbatch)})
        with open(args.json, "w") as f:
            json.dump(out, f)
    dist.destroy_process_group()


# --------------------------------------------------------------------------- the jobs

def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _visible_gpus() -> list[str]:
    """The GPUs this process may use, as CUDA_VISIBLE_DEVICES names them (none: [])."""
    import torch
    if not torch.cuda.is_available():
        return []
    given = os.environ.get("CUDA_VISIBLE_DEVICES")
    if given is not None:
        return [g.strip() for g in given.split(",") if g.strip()]
    return [str(i) for i in range(torch.cuda.device_count())]


def launches(nproc: int, nodes: int) -> list[tuple[list[str], dict[str, str]]]:
    """The torchrun options and environment of each node of a job of `nproc` ranks: one
    `--standalone` process, or `nodes` of the static rendezvous on this host, node i with
    GPUs i*nproc/nodes .. (i+1)*nproc/nodes-1 as its CUDA_VISIBLE_DEVICES (where there are
    GPUs)."""
    # the ddp example imports simloader too: the checkout's, installed or not
    path = os.pathsep.join(filter(None, [str(common.REPO), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, **NCCL_SAFE_ENV, "PYTHONPATH": path}
    if nodes == 1:
        return [(["--standalone", f"--nproc_per_node={nproc}"], env)]
    per, port, gpus = nproc // nodes, _free_port(), _visible_gpus()
    if gpus and len(gpus) < nproc:
        raise SystemExit(f"{nproc} ranks need {nproc} GPUs; {len(gpus)} visible")
    out = []
    for i in range(nodes):
        node_env = dict(env)
        if gpus:
            node_env["CUDA_VISIBLE_DEVICES"] = ",".join(gpus[i * per:(i + 1) * per])
        out.append(([f"--nnodes={nodes}", f"--node-rank={i}", f"--nproc_per_node={per}",
                     "--rdzv-backend=static", "--master-addr=127.0.0.1",
                     f"--master-port={port}"], node_env))
    return out


def _stop(procs) -> None:
    """Ends the torchrun processes this script started, with their ranks (their own sessions)."""
    for proc in procs:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    for proc in procs:
        proc.wait()


def run(nproc: int, nodes: int, args, engine: str, mode: str, workload: str) -> dict:
    """One torchrun job of `nproc` ranks over `nodes` local nodes; rank 0's figures (or why
    it was refused)."""
    what = f"{engine}/{mode} on {nproc} rank(s), {nodes} node(s)"
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "result.json")
        if mode == "ddp":
            w = common.parse_workload(workload)
            command = [str(EXAMPLE), "--backend", ENGINES[engine]["backend"]] + (
                ["--quick"] if args.quick else
                ["--batches", str(args.batches + 5), "--nbatch", str(w.nbatch),
                 "--nstep", str(w.nstep), "--minibatches", "1"])
        else:
            command = [__file__, "--child", "--engine", engine, "--mode", mode,
                       "--workload", workload, "--batches", str(args.batches),
                       "--seed", str(args.seed), "--store", os.path.join(tmp, "s.zarr")]
            if args.deterministic:
                command.append("--deterministic")
        procs, logs = [], []
        binding = [f"--numa-binding={args.numa_binding}"] if args.numa_binding else []
        try:
            for i, (options, env) in enumerate(launches(nproc, nodes)):
                options = options + binding
                out, err = (open(os.path.join(tmp, f"node{i}.{x}"), "w+") for x in "oe")
                logs.append((out, err))
                procs.append(subprocess.Popen(
                    [sys.executable, "-m", "torch.distributed.run", *options, *command,
                     "--json", path], env=env, stdout=out, stderr=err, text=True,
                    start_new_session=True))
            deadline = time.monotonic() + args.job_timeout
            while any(proc.poll() is None for proc in procs):
                if any(proc.poll() for proc in procs):  # a failed node: the others would wait
                    time.sleep(10)  # for it; a refusal ends them all in this time
                    break
                if time.monotonic() > deadline:
                    _stop(procs)
                    raise SystemExit(f"{what} ran past --job-timeout ({args.job_timeout} s):"
                                     f"\n{_tails(logs)}")
                time.sleep(0.2)
        finally:
            _stop(procs)
        codes = [proc.returncode for proc in procs]
        if any(codes) and os.path.exists(path):
            with open(path) as f:
                refused = json.load(f)
            if "refused" in refused:
                _close(logs)
                return refused
        if any(codes):
            text = _tails(logs)
            _close(logs)
            raise SystemExit(f"{what} failed ({codes}):\n{text}")
        _close(logs)
        with open(path) as f:
            return json.load(f)


def _tails(logs) -> str:
    text = []
    for i, (out, err) in enumerate(logs):
        out.seek(0)
        err.seek(0)
        text.append(f"-- node {i} stdout:\n{out.read()[-3000:]}\n-- node {i} stderr:\n"
                    f"{err.read()[-5000:]}")
    return "\n".join(text)


def _close(logs) -> None:
    for out, err in logs:
        out.close()
        err.close()


def _placement(placement) -> str:
    """" (GPUs 0,1; 2,3)": each node's CUDA_VISIBLE_DEVICES, where nodes set them."""
    if not placement:
        return ""
    nodes: dict = {}
    for node, _, gpus in placement:
        nodes.setdefault(node, gpus)
    if len(nodes) < 2 or not any(nodes.values()):
        return ""
    return f" (GPUs {'; '.join(nodes[n] for n in sorted(nodes))})"


def _rows(args, engine: str, mode: str, workload: str, layouts: list) -> list[list]:
    """The table rows of one engine and mode: every (ranks, nodes) layout `--repeats` times,
    interleaved, so that a slow spell of the machine falls on all layouts alike."""
    runs: dict = {layout: [] for layout in layouts}
    for _ in range(args.repeats):
        for nproc, nodes in layouts:
            r = run(nproc, nodes, args, engine, mode, workload)
            if "refused" in r:
                return [[engine, mode, workload, nodes, nproc, "refused: " + r["refused"],
                         *[""] * (6 if args.repeats > 1 else 5)]]
            r.setdefault("per_rank", [r["steps_per_s"] / nproc])
            # each rank's own rate beside its place: which node or GPU holds a job back
            print(f"\n{engine}/{mode}, {nproc} rank(s), {nodes} node(s): per rank "
                  + ", ".join(f"{rate / 1e6:.3g}M" + (f" (node {p[0]}, {p[1]})" if p else "")
                              for rate, p in zip(r["per_rank"], r.get("placement") or
                                                 [None] * len(r["per_rank"]))), flush=True)
            runs[(nproc, nodes)].append(r)
    reference = runs[layouts[0]]
    rows = []
    for (nproc, nodes), rs in runs.items():
        rates = [r["steps_per_s"] for r in rs]
        first = rs[0]
        distinct = "" if mode == "ddp" else "yes" if all(r["distinct"] for r in rs) else "NO"
        again = "" if mode == "ddp" else "; ".join(sorted({r["again"] for r in rs}))
        if mode == "write":
            again += f"; {first['stored']} stored, ranks {first['ranks_in_store']}"
        slowest = statistics.median(min(r["per_rank"]) for r in rs)
        ratio = statistics.median(rates) / statistics.median(r["steps_per_s"] for r in reference)
        figures = [f"{statistics.median(rates) / 1e6:.3g}M", f"{slowest / 1e6:.3g}M",
                   f"{ratio:.2f}x"]
        if args.repeats > 1:
            figures[0] += f" ({min(rates) / 1e6:.3g}M-{max(rates) / 1e6:.3g}M)"
            figures.append(", ".join(f"{r['steps_per_s'] / ref['steps_per_s']:.2f}x"
                                     for r, ref in zip(rs, reference)))
        rows.append([engine, mode, workload, nodes, nproc,
                     first["device"] + _placement(first.get("placement")), *figures,
                     distinct, again])
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--engine", help=argparse.SUPPRESS)
    p.add_argument("--mode", help=argparse.SUPPRESS)
    p.add_argument("--workload", help=argparse.SUPPRESS)
    p.add_argument("--store", help=argparse.SUPPRESS)
    p.add_argument("--json", help=argparse.SUPPRESS)
    p.add_argument("--engines", nargs="+", default=list(ENGINES), choices=list(ENGINES))
    p.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    p.add_argument("--nprocs", type=int, nargs="+", default=[1, 2],
                   help="ranks (GPUs) of each job, all nodes together; the first is the "
                        "reference")
    p.add_argument("--nodes", type=int, nargs="+", default=[1],
                   help="local nodes per job (torchrun's static rendezvous on 127.0.0.1, "
                        "each node its share of the GPUs); several: a job for each --nprocs "
                        "that is a multiple of it")
    p.add_argument("--repeats", type=int, default=1,
                   help="runs of every job, interleaved (all jobs once, then again): a row "
                        "gives the median, the range and each repeat's ratio to the "
                        "reference job of the same repeat")
    p.add_argument("--numa-binding", choices=["node", "socket"],
                   help="torchrun's --numa-binding: each rank on the CPUs of its GPU's NUMA "
                        "node (or socket); a closed loop dispatches every step from Python, so "
                        "its rate follows the cores it lands on")
    p.add_argument("--deterministic", action="store_true",
                   help="SimDataset(deterministic=True): bit-identical batches for a seed, "
                        "or a 'refused' row where the engine cannot (not the ddp example)")
    p.add_argument("--workloads", nargs="+", metavar="ENGINE=MODEL:NBATCHxNSTEP", default=[],
                   help=f"per-rank sizes (default {WORKLOADS}; --quick {QUICK['cpu']})")
    p.add_argument("--batches", type=int, default=8, help="timed batches per rank")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run")
    p.add_argument("--job-timeout", type=float, default=900, help="seconds per torchrun job")
    p.add_argument("--save", action="store_true")
    p.add_argument("--results-dir", type=common.pathlib.Path,
                   default=common.REPO / "benchmarks" / "results")
    p.add_argument("--tag", default="")
    args = p.parse_args()
    if args.child:
        return child(args)
    layouts = [(nproc, nodes) for nproc in args.nprocs for nodes in args.nodes
               if nodes >= 1 and nproc % nodes == 0]
    if len(layouts) < len(args.nprocs) * len(args.nodes) and len(args.nodes) == 1:
        p.error(f"--nodes {args.nodes[0]}: every --nprocs must be a multiple of it")
    if not layouts:
        p.error(f"--nodes {args.nodes}: no --nprocs {args.nprocs} is a multiple of any")
    if args.repeats < 1:
        p.error(f"--repeats {args.repeats}: at least 1")
    if args.numa_binding and not _visible_gpus():
        p.error(f"--numa-binding {args.numa_binding}: binds ranks near their GPUs; this "
                f"machine shows none")
    sizes = {**(QUICK if args.quick else WORKLOADS),
             **dict(item.split("=", 1) for item in args.workloads)}

    rows = []
    jobs = [(e, m) for e in args.engines for m in args.modes if not (m == "ddp" and e == "warp")]
    for engine, mode in common.progress(jobs, desc="engines x modes"):
        workload = QUICK_CAMERA if args.quick and mode == "camera" else sizes[engine]
        rows += _rows(args, engine, mode, workload, layouts)
    headers = ["engine", "mode", "per-rank workload", "nodes", "ranks (all nodes)", "device",
               "steps/s, all ranks", "slowest rank",
               f"vs {layouts[0][0]} rank(s), {layouts[0][1]} node(s)",
               "ranks' streams distinct", "first batch simulated again"]
    if args.repeats > 1:
        headers[6:9] = ["steps/s, all ranks: median (range)", "slowest rank, median",
                        f"vs {layouts[0][0]} rank(s), {layouts[0][1]} node(s): medians",
                        "the same, each repeat"]
    nodes = ("; a job over M > 1 local nodes is M torchrun processes of the static rendezvous, "
             "each node its share of the GPUs" if max(args.nodes) > 1 else "")
    repeats = (f"; every job {args.repeats} times, interleaved (all jobs, then all again)"
               if args.repeats > 1 else "")
    notes = (f"Each row is a torchrun job{nodes}, one process per GPU (or CPU processes "
             f"without GPUs), {args.batches} timed batches per rank after a warm-up batch"
             f"{repeats}; steps/s is all ranks' steps over the slowest rank's time (`ddp`: the "
             f"DDP example's own figure, training included). Simulated again: each rank's first "
             f"batch from (seed, rank, 0); \"bit-equal\" is torch.equal on every key, \"draws "
             f"equal\" initial_state and control bit-equal, \"apart by\" the largest "
             f"|difference| of state over the ranks."
             + (" Datasets built with deterministic=True." if args.deterministic else "")
             + (f" Ranks bound by torchrun --numa-binding={args.numa_binding}."
                if args.numa_binding else ""))
    common.report(args, "scale_out", "Scale-out: engines under torchrun",
                  [notes, common.markdown_table(headers, rows)])


if __name__ == "__main__":
    main()
