"""Soaks (marker `soak`, run only with `--soak`): long streams that must stay healthy.

- `test_memory_stays_flat`: a tiny cart-pole stream (16 x 10, so that simloader's own
  per-batch work, where a leak would hide, dominates the simulation) with random controls and
  initial states. Host RSS and the GPU memory in use (by every process, from the driver) may
  grow by at most GROWTH_LIMIT_MB after the warm-up (the first WARM_UP of the batches), at the
  end and at any sample between; with MJX, no JAX trace or compilation after the first batch.
- `test_episodes_chain_across_batches`: a cart-pole stream with `continue_episodes=True`,
  `terminate=[Outside("hinge", -0.3, 0.3), TimeLimit(LIMIT)]`, checked on every batch: fresh
  frames follow ending frames (across batches too), no episode runs past the time limit, the
  fresh frames' control rows are NaN and every other row finite; host RSS flat as above.
- `test_warp_training_loop` (a CUDA GPU): a training loop fed by a Warp humanoid stream that
  reads a Warp validation stream every third step, with `loss.item()`, `synchronize()` every
  step, bfloat16 autocast, tensors of new shapes and `empty_cache()` every 50 steps: one
  graph capture per dataset, and the floor of the GPU memory the process holds (torch's
  allocator and Warp's pool, sampled just after `empty_cache()`) in the last window no more
  than GROWTH_LIMIT_MB above that of the first window after warm-up.

Each soak runs for SIMLOADER_SOAK_SECONDS seconds if set (default: minutes, see DEFAULT_S),
counted after the first batch (compilation). With SIMLOADER_SOAK_OUT set to a folder, each
writes its measurements there as `<name>.json` (summary and every memory sample).

    python3 -m pytest tests/test_soak.py --soak -k cpu
    SIMLOADER_SOAK_SECONDS=1200 python3 -m pytest tests/test_soak.py --soak -m gpu  # GPU host
"""

from __future__ import annotations

import datetime
import importlib.util
import json
import os
import pathlib
import statistics
import time

import numpy as np
import pytest
import torch

import simloader
from simloader import controls
from simloader import terminate as T

pytestmark = pytest.mark.soak

GROWTH_LIMIT_MB = 50.0
WARM_UP = 0.1  # fraction of the batches before the reference memory sample
LIMIT = 150  # the episodes' time limit (steps)
# default seconds of each soak (SIMLOADER_SOAK_SECONDS overrides them all): about 10^5 batches
# of the tiny stream on the CPU engine, 2,000 episode batches on 2 cores, 20 minutes of Warp
DEFAULT_S = {"stream": 300.0, "episodes": 300.0, "warp": 1200.0}
# JAX's monitoring events of a trace and of an XLA compilation
JAX_COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                      "/jax/core/compile/backend_compile_duration")

NEEDS_GPU = [pytest.mark.gpu,
             pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
             pytest.mark.skipif(importlib.util.find_spec("mujoco_warp") is None,
                                reason="needs mujoco_warp")]
WARP = pytest.param("warp", marks=NEEDS_GPU)


def soak_seconds(kind: str) -> float:
    return float(os.environ.get("SIMLOADER_SOAK_SECONDS") or DEFAULT_S[kind])


def host_rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def gpu_used_mb() -> float:
    """Memory in use on the current GPU by every allocator (JAX's and torch's), from the
    driver; NaN without a GPU."""
    if not torch.cuda.is_available():
        return float("nan")
    free, total = torch.cuda.mem_get_info()
    return (total - free) / 2**20


def growth(samples: list[tuple], column: int) -> tuple[float, float, float]:
    """(end - reference, largest - reference, fitted MB per 10^4 batches) of one column of the
    samples (batches, seconds, values...) from the reference sample, the first at or after
    WARM_UP of the batches delivered; NaNs where the column is NaN (no GPU)."""
    delivered = samples[-1][0]
    start = next(i for i, s in enumerate(samples) if s[0] >= WARM_UP * delivered)
    batch = np.array([s[0] for s in samples[start:]], dtype=float)
    values = np.array([s[column] for s in samples[start:]], dtype=float)
    if np.isnan(values).any():
        return (float("nan"),) * 3
    slope = np.polyfit(batch, values, 1)[0] * 1e4 if len(values) > 2 else float("nan")
    return values[-1] - values[0], values.max() - values[0], slope


def assert_flat(samples: list[tuple], column: int, what: str) -> dict:
    end, peak, trend = growth(samples, column)
    result = {f"{what}_growth_mb": end, f"{what}_peak_growth_mb": peak,
              f"{what}_trend_mb_per_1e4_batches": trend}
    if end == end:  # not NaN
        assert end < GROWTH_LIMIT_MB and peak < GROWTH_LIMIT_MB, (
            f"{what} grew after the warm-up: {end:+.1f} MB at the end, {peak:+.1f} MB at most "
            f"(limit {GROWTH_LIMIT_MB:.0f} MB; trend {trend:+.2f} MB per 10^4 batches)")
    return result


def save(name: str, summary: dict, columns: list[str], samples: list[tuple]) -> None:
    """The measurements as SIMLOADER_SOAK_OUT/<name>.json, when that variable is set; also
    printed (seen with `-s`)."""
    print(f"\n{name}: " + ", ".join(f"{k}={v}" for k, v in summary.items()))
    folder = os.environ.get("SIMLOADER_SOAK_OUT")
    if not folder:
        return
    path = pathlib.Path(folder)
    path.mkdir(parents=True, exist_ok=True)
    record = {"name": name,
              "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU",
              "simloader": getattr(simloader, "__version__", "?"),
              "summary": summary, "columns": columns,
              "samples": [[None if v != v else v for v in s] for s in samples]}
    (path / f"{name}.json").write_text(json.dumps(record, indent=1) + "\n")


class JaxCompilations:
    """Counts JAX traces and XLA compilations in this process from now on (JAX's monitoring
    events: they cover every jitted function, not only simloader's batch function)."""

    def __init__(self) -> None:
        import jax
        self.count = 0
        self._monitoring = jax.monitoring
        self._monitoring.register_event_duration_secs_listener(self._seen)

    def _seen(self, event: str, duration: float, **kwargs) -> None:
        if event in JAX_COMPILE_EVENTS:
            self.count += 1

    def close(self) -> None:
        self._monitoring.unregister_event_duration_listener(self._seen)


@pytest.mark.parametrize("engine", ["cpu", "mjx"])
def test_memory_stays_flat(engine):
    seconds = soak_seconds("stream")
    ds = simloader.SimDataset("cartpole", backend=engine, nbatch=16, nstep=10,
                              control=controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(), seed=0,
                              device="cuda" if torch.cuda.is_available() else None)
    # the first batch of the configuration, in an iterator of its own: it compiles (MJX)
    first = iter(ds)
    next(first)
    first.close()
    compilations = JaxCompilations() if engine == "mjx" else None
    every = max(0.05, seconds / 200)  # a memory sample this often (seconds)
    samples = []  # (batches delivered, seconds, host RSS MB, GPU MB)
    delivered, checksum = 0, 0.0
    stream = iter(ds)
    start = time.perf_counter()
    try:
        for batch in stream:
            delivered += 1
            now = time.perf_counter() - start
            done = now >= seconds and delivered >= 10
            if not samples or done or now - samples[-1][1] >= every:
                checksum += float(batch["state"][0, -1, 1])  # touch the data (synchronizes)
                samples.append((delivered, now, host_rss_mb(), gpu_used_mb()))
            if done:
                break
    finally:
        stream.close()
        if compilations is not None:
            compilations.close()
    assert checksum == checksum, "the stream delivered NaN states"
    summary = {"engine": engine, "batches": delivered, "seconds": round(samples[-1][1], 1),
               "batches_per_s": round(delivered / samples[-1][1], 1),
               "diverged": ds.stats["diverged"], "compiles": ds.stats.get("compiles", 0)}
    try:
        summary.update(assert_flat(samples, 2, "host_rss"))
        summary.update(assert_flat(samples, 3, "gpu"))
        if compilations is not None:
            summary["jax_compilations_after_first_batch"] = compilations.count
            assert compilations.count == 0, (
                f"{compilations.count} JAX traces or compilations after the first batch")
    finally:
        save(f"soak-{engine}", summary, ["batches", "seconds", "host_rss_mb", "gpu_mb"],
             samples)


@pytest.mark.parametrize("engine", ["cpu", "mjx", WARP])
def test_episodes_chain_across_batches(engine):
    seconds = soak_seconds("episodes")
    nbatch, nstep = 256, 100
    ds = simloader.SimDataset("cartpole", nbatch=nbatch, nstep=nstep, seed=0, backend=engine,
                              control=controls.Uniform(), continue_episodes=True,
                              terminate=[T.Outside("hinge", -0.3, 0.3), T.TimeLimit(LIMIT)])
    since = torch.zeros(nbatch, dtype=torch.int64)  # steps since each trajectory's fresh start
    ended_last = torch.zeros(nbatch, dtype=torch.bool)  # the previous batch's last frame ended
    counts = dict(resets=0, terminated=0, truncated=0, steps=0)
    every = max(0.05, seconds / 100)
    samples = []  # (batches, seconds, host RSS MB)
    stream = iter(ds)
    start = None
    try:
        for i, batch in enumerate(stream, start=1):
            b = {k: v.cpu() for k, v in batch.items() if isinstance(v, torch.Tensor)}
            first, term, trunc = b["first"], b["terminated"], b["truncated"]
            ended = term | trunc
            # the flags chain across batches: a fresh frame follows an ending frame, only then
            chained = torch.cat([ended_last[:, None], ended[:, :-1]], dim=1)
            assert torch.equal(first, chained), f"batch {i}: fresh frames not after ending ones"
            ended_last = ended[:, -1].clone()
            nan = torch.isnan(b["control"]).any(dim=-1)
            assert torch.equal(nan, first), f"batch {i}: a fresh frame's control was applied"
            assert torch.isfinite(b["control"][~first]).all(), f"batch {i}: a non-finite control"
            for j in range(nstep):
                since = torch.where(first[:, j], 0, since + 1)
                assert int(since.max()) <= LIMIT, f"batch {i}: an episode ran past the limit"
            counts["resets"] += int(first.sum())
            counts["terminated"] += int(term.sum())
            counts["truncated"] += int(trunc.sum())
            counts["steps"] += b["state"].shape[0] * b["state"].shape[1]
            if start is None:  # the clock starts after the first batch (compilation)
                start = time.perf_counter()
            now = time.perf_counter() - start
            done = now >= seconds and i >= 10
            if not samples or done or now - samples[-1][1] >= every:
                samples.append((i, now, host_rss_mb()))
            if done:
                break
    finally:
        stream.close()
    summary = {"engine": engine, "batches": samples[-1][0], "seconds": round(samples[-1][1], 1),
               **counts, "mean_episode_steps": round(counts["steps"] / max(counts["resets"], 1),
                                                     1)}
    try:
        assert counts["resets"] > 0 and counts["terminated"] > 0, "no episode ended"
        summary.update(assert_flat(samples, 2, "host_rss"))
    finally:
        save(f"soak_episodes-{engine}", summary, ["batches", "seconds", "host_rss_mb"], samples)


def memory_windows(samples: list[tuple[float, float]], minutes: float
                   ) -> tuple[list[float], list[float], float]:
    """The values of the first window after warm-up and of the last window (minutes), and the
    window's length. Samples are taken just after `empty_cache()`, where the loop holds only
    what is alive; what is alive still steps with the batches in flight (0 to the prefetch
    depth per stream: one 4096 x 50 humanoid batch is ~45 MB), so the floor of a window (its
    fewest batches in flight) is what a leak would lift."""
    warm, window = min(1.0, minutes / 4), max(minutes / 10, 0.05)
    end = samples[-1][0]
    early = [g for m, g in samples if warm <= m <= warm + window]
    late = [g for m, g in samples if m >= end - window]
    return early or [samples[0][1]], late, window


@pytest.mark.parametrize("engine", [WARP])
def test_warp_training_loop(engine):
    import warp as wp

    minutes = soak_seconds("warp") / 60
    nbatch, nstep = 4096, 50
    kwargs = dict(backend=engine, control=controls.Uniform())
    train = simloader.SimDataset("humanoid", nbatch=nbatch, nstep=nstep, **kwargs)
    valid = simloader.SimDataset("humanoid", nbatch=nbatch // 4, nstep=nstep, seed=1, **kwargs)
    nstate = train.config.nstate
    model = torch.nn.Sequential(torch.nn.Linear(nstate, 256), torch.nn.ReLU(),
                                torch.nn.Linear(256, nstate)).cuda()
    opt = torch.optim.Adam(model.parameters(), 1e-3)
    it, vit = iter(train), iter(valid)
    start, held, allocated, step = time.perf_counter(), [], [], 0

    def elapsed_minutes() -> float:
        return (time.perf_counter() - start) / 60

    def held_gib() -> float:
        """GiB this process holds on the GPU: torch's caching allocator and Warp's memory pool
        (MuJoCo Warp's arrays, what its graph captures allocate). Unlike the device's used
        memory, no other process on the GPU moves it."""
        return (torch.cuda.memory_reserved() + wp.get_mempool_used_mem_current("cuda:0")) / 2**30

    try:
        while elapsed_minutes() < minutes:
            batch = next(it)
            x = batch["state"][:, :-1].reshape(-1, nstate)[: 50000 + 13 * (step % 100)]
            y = batch["state"][:, 1:].reshape(-1, nstate)[: x.shape[0]]
            with torch.autocast("cuda", dtype=torch.bfloat16):
                loss = (model(x) - y).float().pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            loss.item()
            torch.cuda.synchronize()
            if step % 3 == 0:
                with torch.no_grad():
                    model(next(vit)["state"].reshape(-1, nstate)).mean().item()
            if step % 50 == 0:
                torch.cuda.empty_cache()
                held.append((elapsed_minutes(), held_gib()))
                allocated.append((elapsed_minutes(), torch.cuda.memory_allocated() / 2**30))
            step += 1
    finally:
        it.close()
        vit.close()
    summary = {"minutes": round(elapsed_minutes(), 2), "training_steps": step,
               "train_batches": train.stats["batches"], "valid_batches": valid.stats["batches"],
               "steps_simulated": train.stats["steps"] + valid.stats["steps"],
               "graph_captures": [train.stats["graph_captures"], valid.stats["graph_captures"]],
               "overflow": [train.stats.get("overflow", 0), valid.stats.get("overflow", 0)]}
    early, late, window = memory_windows(held, minutes)
    summary.update({"window_minutes": window, "samples": len(held),
                    "held_floor_early_gib": min(early), "held_floor_late_gib": min(late),
                    "held_median_early_gib": statistics.median(early),
                    "held_median_late_gib": statistics.median(late)})
    early_live, late_live, _ = memory_windows(allocated, minutes)
    summary.update({"live_floor_early_gib": min(early_live),
                    "live_floor_late_gib": min(late_live)})
    save("soak_warp", summary, ["minutes", "held_gib", "torch_allocated_gib"],
         [(m, g, a) for (m, g), (_, a) in zip(held, allocated)])
    assert train.stats["graph_captures"] == 1 and valid.stats["graph_captures"] == 1, (
        f"graph captures (train, validation): {summary['graph_captures']}, not one each")
    grew = (min(late) - min(early)) * 1024
    assert grew < GROWTH_LIMIT_MB, (
        f"the GPU memory held grew: its floor {min(early):.3f} GiB in the first {window:.1f} "
        f"min after warm-up, {min(late):.3f} GiB in the last ({grew:+.1f} MB, limit "
        f"{GROWTH_LIMIT_MB:.0f} MB)")
