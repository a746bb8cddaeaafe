"""`simloader bench run`: the workloads of `workloads.py` measured, checked, written as JSON lines.

Each workload builds its two sides (`build`), times them alternately (`timing.interleave`, the
order reversed every repetition, medians; a workload below its target is timed again as many
times and judged on all its repetitions), and gives one result line per side: units per
second, the subject's ratio to the baseline, the target and whether it holds, the time to the
first batch, memory, the machine, the commit and the versions (`results.py` reads and renders
them). Start-up is timed apart from the steady state: each side's first batch (compilation and
graph capture included) is `first_s`, never part of a rate.
"""

from __future__ import annotations

import dataclasses
import datetime
import os
import pathlib
import resource
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from typing import Any, Optional

import mujoco
import torch

from simloader.bench import raw as R
from simloader.bench import startup, timing
from simloader.bench.datasets import camera_of, dataset, options
from simloader.bench import workloads as W
from simloader.bench.workloads import Benchmark, Method, Stream


@dataclasses.dataclass
class Side:
    """One built side of a comparison.

    `measure(n)` times `n` calls (batches, or fresh processes for start-up) and returns seconds
    per unit; `first_s` is the time to the first batch (compilation included); `call_s` one
    warm call, to size the repetitions; `close` releases what it holds.
    """

    measure: Callable[[int], float]
    first_s: float
    call_s: float
    close: Callable[[], None] = lambda: None
    extra: dict = dataclasses.field(default_factory=dict)


def _timed(measure: Callable[[int], float], steps: int,
           close: Callable[[], None] = lambda: None) -> Side:
    """A side whose first call (warm-up: compilation, pools, workers) is its `first_s`."""
    start = time.perf_counter()
    measure(1)
    first = time.perf_counter() - start
    return Side(measure, first, measure(1) * steps, close=close)


def sizes(s: Stream) -> R.Workload:
    return R.Workload(s.model, s.nbatch, s.nstep)


def delivered(s: Stream, model: mujoco.MjModel, seed: int) -> timing.SimloaderMeasure:
    return timing.SimloaderMeasure(model, sizes(s), s.engine, seed, **options(s, model))


def _from_measure(m: timing.SimloaderMeasure, steps: int) -> Side:
    return Side(lambda n: m.measure(n), m.first_s, m.measure(1) * steps)


# -- the sides ----------------------------------------------------------------------------------

def _raw(s: Stream, model: mujoco.MjModel, seed: int, continued: bool) -> Side:
    w = sizes(s)
    if s.engine == "cpu":
        if continued:
            raise ValueError(f"{s}: the raw CPU baseline restarts its trajectories")
        if s.camera is None:
            measure, batch_s = R.raw_rollout(model, w, timing.cpu_count(), seed)
            return Side(measure, batch_s, batch_s)
        # simulate, then render every state (what the stream does), on as many threads
        from simloader import render
        platform = render.gl_platform()[1]  # the platform simloader's renderers use
        renderers = R.RawRenderers(model, 0, s.camera[0], timing.cpu_count(),
                                   gl=platform if platform in ("egl", "osmesa") else None,
                                   shadows=s.camera_quality, multisample=s.camera_quality)
        start = time.perf_counter()
        measure, batch_s = R.raw_rollout(model, w, timing.cpu_count(), seed, render=renderers)
        return Side(measure, time.perf_counter() - start, batch_s,
                    close=lambda: renderers.pool.shutdown())
    if s.engine == "mjx":
        if continued or s.camera is not None:
            raise ValueError(f"{s}: the raw MJX baseline has no continued worlds or cameras")
        r = R.RawMjx(model, w, seed)
    else:
        if s.camera is not None and s.camera != (64, 64):
            raise ValueError(f"{s}: the raw Warp baseline renders 64 x 64 only")
        resolved = dataset(s, model, seed).config.options
        r = R.RawWarp.matching(model, w, seed, resolved, cameras=s.camera is not None,
                               continued=continued)
    return Side(r.measure, r.first_s, r.batch_s)


def _write(s: Stream, model: mujoco.MjModel, seed: int, folder: pathlib.Path) -> Side:
    """`simloader.write` of `n` batches into a fresh store of ours, removed after timing."""
    import simloader
    ds = dataset(s, model, seed)
    count = [0]

    def measure(n: int) -> float:
        count[0] += 1
        path = folder / f"write-{count[0]}.zarr"
        timing.sync()
        start = time.perf_counter()
        simloader.write(ds, path, batches=n, progress=False)
        seconds = time.perf_counter() - start
        shutil.rmtree(path)  # a store this run made, in the folder it made
        timing.drain()
        return seconds / (n * s.steps)

    return _timed(measure, s.steps)


def disk_seconds_per_byte(folder: pathlib.Path, nbytes: int) -> float:
    """Sequential write of `nbytes` into `folder` then `fdatasync` (`dd bs=1M conv=fdatasync`)."""
    block = b"\0" * (1 << 20)
    path = folder / "disk-speed.bin"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        start = time.perf_counter()
        for _ in range(max(1, nbytes >> 20)):
            os.write(fd, block)
        os.fdatasync(fd)
        seconds = time.perf_counter() - start
    finally:
        os.close(fd)
        os.unlink(path)
    return seconds / (max(1, nbytes >> 20) << 20)


def store_bytes(path: pathlib.Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _write_bound(s: Stream, model: mujoco.MjModel, seed: int, folder: pathlib.Path) -> Side:
    """The lower of generating the stream (delivered) and the disk's bound for its bytes: per
    step, the larger of the generation's seconds and the disk's seconds for a step's bytes."""
    import simloader
    gen = delivered(s, model, seed)
    # (its own dataset writes a store to learn the bytes per step: no second compilation)
    path = simloader.write(gen.ds, folder / "bytes-per-step.zarr", batches=2, progress=False)
    per_step = store_bytes(pathlib.Path(path)) / (2 * s.steps)
    shutil.rmtree(path)
    extra: dict[str, Any] = {"store_bytes_per_step": per_step}

    def measure(n: int) -> float:
        generation = gen.measure(n)
        disk = disk_seconds_per_byte(folder, min(int(per_step * n * s.steps), 4 << 30)) * per_step
        extra.setdefault("generation_steps_per_s", []).append(1 / generation)
        extra.setdefault("disk_steps_per_s", []).append(1 / disk)
        return max(generation, disk)

    return Side(measure, gen.first_s, gen.measure(1) * s.steps, extra=extra)


READ_WORKERS = 2  # the CPU renderer's DataLoader workers (target 15: "2 workers")


def _read_render(s: Stream, model: mujoco.MjModel, seed: int, folder: pathlib.Path) -> Side:
    """A store of the stream's states (no images) rendering its camera on read: on the CPU a
    `DataLoader` of trajectories with `READ_WORKERS` workers, on a GPU
    `transitions().loader(4096)` (both frames of each transition)."""
    import simloader
    if s.camera is None:
        raise ValueError(f"{s}: rendering on read needs a camera")
    states = dataset(s.but(camera=None), model, seed, record=("state",))
    path = simloader.write(states, folder / "states.zarr", batches=2, progress=False)
    camera = camera_of(s)
    if s.engine == "cpu":
        stored = simloader.StoredDataset(path, cameras=camera, keys=["state"])
        workers = READ_WORKERS
        loader = torch.utils.data.DataLoader(
            stored, batch_size=8, shuffle=True, num_workers=workers,
            persistent_workers=workers > 0, multiprocessing_context="spawn" if workers else None)
        per_item = s.nstep
    else:
        stored = simloader.StoredDataset(path, cameras=camera, backend=s.engine, device="cuda",
                                         keys=["state"])
        transitions = stored.transitions()
        loader = transitions.loader(min(4096, len(transitions)), order="random")
        per_item = 2

    return _timed(lambda n: timing.read_frames(loader, n * s.steps, per_item), s.steps,
                  close=lambda: shutil.rmtree(path))


def _mixture(b: Benchmark, models: list, seed: int) -> tuple[Side, Side]:
    """A `Mixture` of the streams (equal weights) against the same batches each streamed alone:
    the baseline's time is the sum, over the batches the mixture drew, of each member's own
    seconds per batch (measured alone in the same repetition), and its steps the same."""
    import simloader
    streams = b.subject.streams
    alone = [delivered(s, m, seed + i) for i, (s, m) in enumerate(zip(streams, models))]
    mixed = [dataset(s, m, seed + 10 + i) for i, (s, m) in enumerate(zip(streams, models))]
    mixture = simloader.Mixture(mixed, seed=seed)
    draws: list[int] = []

    def measure_mixture(n: int) -> float:
        draws.clear()
        steady = timing.time_stream(mixture, n, on_batch=lambda batch: draws.append(
            int(batch["task"].reshape(-1)[0]))).steady_s
        return steady / sum(streams[i].steps for i in draws)

    def measure_members(n: int) -> float:
        batch_s = [m.measure(n) * s.steps for m, s in zip(alone, streams)]
        chosen = draws or list(range(len(streams)))  # before the mixture's first repetition
        return (sum(batch_s[i] for i in chosen) / sum(streams[i].steps for i in chosen))

    start = time.perf_counter()
    call = measure_mixture(1) * statistics.mean(s.steps for s in streams)
    first = time.perf_counter() - start
    members = Side(measure_members, max(m.first_s for m in alone),
                   sum(m.measure(1) * s.steps for m, s in zip(alone, streams)))
    return Side(measure_mixture, first, call), members


def _startup(s: Stream, raw: bool, folder: pathlib.Path, seed: int, timeout: float) -> Side:
    """Fresh processes to their first batch, with the user's caches (Warp's kernels, CUDA's)
    and a JAX compilation cache of their own: one child first to fill them (its time is
    `first_s`), then each call a warm child. A call's result is the median, over its children,
    of their seconds after `import torch` ended (`extra["after_torch_s"]`); the seconds before
    (`extra["before_torch_s"]`: the interpreter and `import torch`) are added by `run_one`,
    pooled over both sides (`startup_seconds`)."""
    import simloader
    root = folder / ("startup-raw" if raw else "startup-simloader")
    root.mkdir()
    spec = {"model": str(simloader.models.builtin_path(s.model)), "nbatch": s.nbatch,
            "nstep": s.nstep, "seed": seed, "backend": s.engine, "jax_cache": str(root / "jax"),
            # the same work as the raw script: all the cores on the CPU engine
            "options": {"nthread": timing.cpu_count()} if s.engine == "cpu" and s.all_cores
            else {}}
    script = startup.RAW_SCRIPT[s.engine] if raw else startup.SIMLOADER
    extra: dict[str, Any] = {"after_torch_s": [], "before_torch_s": []}

    def child() -> float:
        out = startup.run_child(script, root, spec, simloader=not raw, timeout=timeout,
                                isolate=False)
        if "error" in out:
            raise RuntimeError(f"{'raw' if raw else 'simloader'} start-up child: {out['error']}")
        extra["after_torch_s"].append(out["after_torch"])
        extra["before_torch_s"].append(out["total"] - out["after_torch"])
        return out["after_torch"]

    child()
    extra["filling_caches_s"] = extra["before_torch_s"][0] + extra["after_torch_s"][0]
    extra["after_torch_s"].clear()
    extra["before_torch_s"].clear()
    return Side(lambda n: statistics.median(child() for _ in range(n)),
                extra["filling_caches_s"], extra["filling_caches_s"], extra=extra)


def _ranks(s: Stream, count: int, seed: int, timeout: float) -> Side:
    """`count` processes under torchrun, one per GPU, each streaming `s` (its own part of one
    seeded stream): seconds per step per GPU, all ranks' steps over the slowest rank's time.
    Each call is a fresh job (`ranks.job`) timing its batches after a warm-up one; the first
    job fills the caches (its wall time is `first_s`)."""
    from simloader.bench import ranks
    # the slowest rank's steps/s of each job (its per-GPU rate is what is compared); the
    # medians `run_one` writes are of numbers
    extra: dict[str, Any] = {"slowest_rank_steps_per_s": [], "fastest_rank_steps_per_s": []}

    def call(n: int) -> float:
        got = ranks.job(s, count, n, seed, timeout)
        if not got["distinct"]:
            raise RuntimeError(f"{count} ranks of {s}: the ranks drew the same batches")
        devices = got["devices"]
        if devices[0] != "cpu" and len(set(devices)) != count:
            # ranks sharing a GPU would read as poor scaling
            raise RuntimeError(f"{count} ranks of {s}: ranks on the same GPU: {devices}")
        extra["slowest_rank_steps_per_s"].append(min(got["per_rank"]))
        extra["fastest_rank_steps_per_s"].append(max(got["per_rank"]))
        return 1 / got["per_gpu"]

    start = time.perf_counter()
    per_step = call(1)
    first = time.perf_counter() - start
    for values in extra.values():
        values.clear()
    return Side(call, first, per_step * s.steps, extra=extra)


def _sim_devices(s: Stream, count: int, model: mujoco.MjModel, seed: int) -> Side:
    """`count` simulation GPUs (cuda:1 ..) each simulating `s`'s trajectories of a batch
    `count` times as large, delivered on cuda:0 (`sim_device=`): seconds per step per
    simulation GPU (`run` skips it on a machine without `count + 1` GPUs:
    `Method.gpus`)."""
    m = timing.SimloaderMeasure(
        model, R.Workload(s.model, s.nbatch * count, s.nstep), s.engine, seed,
        **options(s, model), device="cuda:0",
        sim_device=[f"cuda:{i}" for i in range(1, count + 1)])
    return Side(lambda n: m.measure(n) * count, m.first_s, m.measure(1) * s.steps * count)


def startup_seconds(after: dict[str, float], subject: Side, baseline: Side) -> dict[str, float]:
    """Seconds from a process's start to its first batch, per side: its median seconds after
    `import torch` (`after`) plus the median, pooled over both sides' children, of the seconds
    before. Both children run the same script text up to there (`startup.PRELUDE`), so its
    differences are the machine's (0.4 s apart between two runs' medians on an H200, against a
    5% target of 0.26 s), not simloader's: pooled, they weigh alike on both sides."""
    before = subject.extra["before_torch_s"] + baseline.extra["before_torch_s"]
    shared = statistics.median(before)
    for side in (subject, baseline):  # what was added, in both sides' lines
        side.extra["before_torch_pooled_s"] = shared
    return {role: seconds + shared for role, seconds in after.items()}


def _seconds(b: Benchmark, each: dict[str, list[float]], subject: Side, baseline: Side
             ) -> tuple[dict[str, float], dict[str, list[float]]]:
    """Each side's median seconds per unit over the repetitions `each`, and the repetitions
    as the medians counted them (a start-up's with the pooled seconds before `import torch`
    added, `startup_seconds`)."""
    s = {k: statistics.median(v) for k, v in each.items()}
    if b.subject.kind == W.STARTUP and b.baseline.kind == W.RAW_STARTUP:
        s = startup_seconds(s, subject, baseline)
        shared = subject.extra["before_torch_pooled_s"]  # as the medians got it
        each = {k: [v + shared for v in values] for k, values in each.items()}
    return s, each


def build(b: Benchmark, seed: int, folder: pathlib.Path, timeout: float) -> tuple[Side, Side]:
    """The subject and baseline of `b`, built (compiled, warmed up) and ready to time."""
    import simloader
    names = {s.model for m in (b.subject, b.baseline) for s in m.streams}
    loaded = {name: simloader.load_model(name) for name in names}  # each once
    if b.subject.kind == W.MIXTURE:
        return _mixture(b, [loaded[s.model] for s in b.subject.streams], seed)

    def side(m: Method) -> Side:
        s = m.streams[0]
        model = loaded[s.model]
        if m.kind == W.SIMLOADER:
            return _from_measure(delivered(s, model, seed), s.steps)
        if m.kind in (W.RAW, W.RAW_CONTINUED):
            return _raw(s, model, seed, continued=m.kind == W.RAW_CONTINUED)
        if m.kind == W.WRITE:
            return _write(s, model, seed, folder)
        if m.kind == W.WRITE_BOUND:
            return _write_bound(s, model, seed, folder)
        if m.kind == W.READ_RENDER:
            return _read_render(s, model, seed, folder)
        if m.kind in (W.STARTUP, W.RAW_STARTUP):
            return _startup(s, m.kind == W.RAW_STARTUP, folder, seed, timeout)
        if m.kind == W.RANKS:
            return _ranks(s, m.count, seed, timeout)
        if m.kind == W.SIM_DEVICES:
            return _sim_devices(s, m.count, model, seed)
        raise ValueError(f"{b.name}: no way to measure {m.kind!r}")

    return side(b.subject), side(b.baseline)


# -- the run --------------------------------------------------------------------------------------

def machine() -> dict[str, Any]:
    """Where the run is: the GPU's name (or "CPU"), cores, host memory."""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"device": gpu or "CPU", "gpus": torch.cuda.device_count(),
            "cpus": timing.cpu_count(),
            "memory_gib": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
                                / 2 ** 30, 1)}


def versions() -> dict[str, Optional[str]]:
    from importlib import metadata

    import simloader
    out: dict[str, Optional[str]] = {"simloader": simloader.__version__}
    for name in ("mujoco", "mujoco-mjx", "jax", "mujoco-warp", "warp-lang", "torch", "zarr"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def commit() -> dict[str, Any]:
    """The checkout's commit and whether its tracked files differ from it (None outside git)."""
    import subprocess
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=startup.REPO, text=True,
                              capture_output=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=startup.REPO, text=True, capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return {"commit": None, "dirty": None}
    if head.returncode != 0:
        return {"commit": None, "dirty": None}
    return {"commit": head.stdout.strip(), "dirty": bool(dirty.stdout.strip())}


def memory() -> dict[str, Optional[int]]:
    """The process's peak resident memory so far, and the GPU's memory in use now (every
    allocator: torch's, JAX's, Warp's), in bytes."""
    out: dict[str, Optional[int]] = {
        "host_peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}
    if torch.cuda.is_available():
        free, total = torch.cuda.mem_get_info()
        out["gpu_used_bytes"] = total - free
    return out


def where() -> dict[str, Any]:
    """The fields every line of a run shares: machine, commit, versions (asked once a run)."""
    return {"machine": machine(), **commit(), "versions": versions()}


def run_one(b: Benchmark, *, repeats: int, min_seconds: float, seed: int,
            folder: pathlib.Path, timeout: float,
            here: Optional[dict[str, Any]] = None) -> list[dict[str, Any]]:
    """Two result lines (subject, baseline) of one workload (`here`: `where()`, once a run)."""
    own = folder / b.name
    own.mkdir()
    began = time.perf_counter()
    subject, baseline = build(b, seed, own, timeout)
    try:
        startup_kind = b.subject.kind == W.STARTUP
        # start-up: `min_calls` fresh processes per repetition (their median)
        n = b.min_calls if startup_kind else timing.batches_for(
            max(subject.call_s, baseline.call_s), b.min_calls, min_seconds)
        measures = {"subject": lambda: subject.measure(n), "baseline": lambda: baseline.measure(n)}
        each: dict[str, list[float]] = {}
        timing.interleave(measures, repeats, desc=b.name, each=each)
        s, pooled = _seconds(b, each, subject, baseline)
        again = 0
        if b.target is not None and s["baseline"] / s["subject"] < b.target:
            # below its target: as many repetitions again, pooled with the first, before the
            # verdict (on a machine whose repetitions of the same work move by more than the
            # target's allowance, one draw of medians misses by chance; a real shortfall
            # stays below with twice the repetitions)
            more: dict[str, list[float]] = {}
            timing.interleave(measures, repeats, desc=f"{b.name} (below its target: again)",
                              each=more)
            each = {k: each[k] + more[k] for k in each}
            again = repeats
            s, pooled = _seconds(b, each, subject, baseline)
        each = pooled
    finally:
        subject.close()
        baseline.close()
    rate = {k: 1 / v for k, v in s.items()}
    ratio = rate["subject"] / rate["baseline"]
    ok = b.target is None or ratio >= b.target
    after = subject.extra.get("after_torch_s")
    if b.ceiling_s is not None and after:
        ok = ok and statistics.median(after) <= b.ceiling_s
    common = {"workload": b.name, "suite": b.suite, "unit": b.unit, "target": b.target,
              "ceiling_s": b.ceiling_s, "source": b.source, "repeats": repeats + again,
              "repeated_below_target": again,
              "calls_per_repeat": n, "wall_s": time.perf_counter() - began,
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              **(here if here is not None else where()), "memory": memory()}
    lines = []
    for role, side, method in (("subject", subject, b.subject),
                               ("baseline", baseline, b.baseline)):
        lines.append({**common, "role": role, "method": str(method),
                      "units_per_s": rate[role], "first_s": side.first_s,
                      # each repetition's seconds per unit, in the order run: how much the
                      # machine moved (their median is the line's rate)
                      "repetitions_s": each[role],
                      "ratio": ratio if role == "subject" else None,
                      "passed": ok if role == "subject" else None,
                      "extra": {k: (statistics.median(v) if isinstance(v, list) and v else v)
                                for k, v in side.extra.items()}})
    return lines


def run(benchmarks: Sequence[Benchmark], out: pathlib.Path, *, repeats: int = 3,
        min_seconds: float = 1.5, seed: int = 0, folder: Optional[str] = None,
        timeout: float = 300.0, on_line: Callable[[dict], None] = lambda line: None,
        ) -> list[dict[str, Any]]:
    """Runs the workloads one after another, appending each one's lines to `out` (JSON lines) as
    it finishes, so that a run cut short keeps what it measured.

    Args:
      folder: where the stores and start-up caches go: a temporary folder made inside it (the
        system's by default) and removed at the end; nothing else in it is touched.

    Returns:
      every line written; a workload that failed gives a subject line with `error`.
    """
    from simloader.bench import results
    lines: list[dict[str, Any]] = []
    work = pathlib.Path(tempfile.mkdtemp(prefix="simloader-bench-", dir=folder))
    here = where()
    try:
        for b in timing.progress(benchmarks, desc="workloads", total=len(benchmarks)):
            try:
                if b.gpus > here["machine"]["gpus"]:
                    # a fact about this machine, not a result: neither a pass nor a failure
                    got = [{"workload": b.name, "suite": b.suite, "role": "subject",
                            "target": b.target, "passed": None,
                            "skipped": f"needs {b.gpus} GPUs; this machine has "
                                       f"{here['machine']['gpus']}",
                            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
                                timespec="seconds"), **here}]
                else:
                    got = run_one(b, repeats=repeats, min_seconds=min_seconds, seed=seed,
                                  folder=work, timeout=timeout, here=here)
            except Exception as e:  # one workload's failure is a result, not the end of the run
                got = [{"workload": b.name, "suite": b.suite, "role": "subject",
                        "target": b.target, "passed": False, "error": f"{type(e).__name__}: {e}",
                        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(
                            timespec="seconds"), **here}]
            results.append_lines(out, got)
            for line in got:
                on_line(line)
            lines += got
    finally:
        shutil.rmtree(work, ignore_errors=True)  # the folder this run made, nothing else
    return lines
