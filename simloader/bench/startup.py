"""Fresh processes to their first batch: the child scripts of `simloader bench run`'s start-up
workloads and of `benchmarks/bench_startup.py`.

Each child is a self-contained script run as `python -c`, doing what a user's script does from
interpreter start to the first batch in torch's hands, timed in phases (`PHASES`) and printed as
one JSON line. The raw scripts import neither simloader nor benchmarks/: they are the recipes of
`simloader.bench.raw` (`RawMjx`, `RawWarp`, `raw_rollout`), written out. Each child gets cache
folders of its own under a root (`XDG_CACHE_HOME`, `JAX_COMPILATION_CACHE_DIR`, `WARP_CACHE_PATH`,
`CUDA_CACHE_PATH`): empty for a cold run, reused for warm ones.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import time
from typing import Any, Optional

# the checkout (or site-packages folder) this package is in: the simloader children import
REPO = pathlib.Path(__file__).resolve().parents[2]
PHASES = ("startup", "import_torch", "import_engine", "construct", "trace", "compile",
          "first_sim", "handoff")
CPU_AFTER_TORCH_S = 0.5  # rollout: simloader's first batch at most this after torch's import

# -- the children: self-contained scripts, run as `python -c` -----------------------------------

PRELUDE = r'''
import json, os, sys, time
_OFF = max(0.0, time.time() - float(os.environ["BENCH_STARTUP_T0"]))
_PC0 = time.perf_counter() - _OFF
P = {"startup": _OFF}
X = {}
_LAST = [time.perf_counter()]
def mark(name):
    now = time.perf_counter()
    P[name] = now - _LAST[0]
    _LAST[0] = now
    return now
SPEC = json.loads(os.environ["BENCH_STARTUP_SPEC"])
def finish():
    now = time.perf_counter()
    if _PROFILE:  # after the clock: writing the stacks is not the child's time
        _profiled()
    out = {"phases": P, "total": now - _PC0, "after_torch": now - t_torch, "extra": X}
    sys.stdout.flush()
    print("\n" + json.dumps(out), flush=True)
def handed_over(first):
    """The first batch ({key: tensor}) is in torch's hands: its device and shape, the line."""
    X["device"] = str(next(iter(first.values())).device)
    X["shape"] = list(first["state"].shape) if "state" in first else None
    finish()
_PROFILE = os.environ.get("BENCH_STARTUP_PROFILE")
if _PROFILE:
    # where the seconds after `import torch` go, every thread's (simloader's first batch is
    # made on its prefetch thread, which a cProfile of the main thread would not see): a
    # thread samples every other thread's Python stack about every _EVERY seconds, each
    # sample weighted by the microseconds since the sampler's last pass (a pass waits for
    # the GIL: counting passes would undercount); written as folded stacks
    # ("thread;file:function;... microseconds") for a flame graph or a summary
    import collections, threading
    _EVERY = 0.002
    _STACKS = collections.Counter()
    _STOP = threading.Event()
    def _label(code):
        parts = code.co_filename.replace(os.sep, "/").split("/")
        return "/".join(parts[-2:]) + ":" + getattr(code, "co_qualname", code.co_name)
    def _sampler():
        me = threading.get_ident()
        last = time.perf_counter()
        while not _STOP.wait(_EVERY):
            now = time.perf_counter()
            weight, last = round((now - last) * 1e6), now
            names = {t.ident: t.name.replace(";", ":") for t in threading.enumerate()}
            for tid, frame in sys._current_frames().items():
                if tid == me:
                    continue
                stack = []
                while frame is not None:
                    stack.append(_label(frame.f_code).replace(";", ":"))
                    frame = frame.f_back
                _STACKS[";".join([names.get(tid, "thread"), *reversed(stack)])] += weight
    def _profiled():
        _STOP.set()
        _SAMPLER.join()  # its last pass finished: nothing added after the file is written
        with open(_PROFILE, "w") as f:
            f.writelines(f"{k} {v}\n" for k, v in _STACKS.most_common())
        X["profile"] = {"file": os.path.basename(_PROFILE), "unit_s": 1e-6,
                        "every_s": _EVERY}
import torch  # first, as a torch user has it
t_torch = mark("import_torch")
if _PROFILE:
    _SAMPLER = threading.Thread(target=_sampler, name="bench-sampler", daemon=True)
    _SAMPLER.start()
'''

RAW_JAX = PRELUDE + r'''
import contextlib, io
import jax
import jax.numpy as jnp
import mujoco
with contextlib.redirect_stdout(io.StringIO()):  # mjx's "Failed to import warp" print
    from mujoco import mjx
mark("import_engine")
jax.config.update("jax_compilation_cache_dir", SPEC["jax_cache"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
m = mujoco.MjModel.from_xml_path(SPEC["model"])
mx = mjx.put_model(m, impl="jax")
d0 = mjx.make_data(mx, impl="jax")  # the state mj_resetData gives
jax.block_until_ready(d0)
mark("construct")
nbatch, nstep, nu = SPEC["nbatch"], SPEC["nstep"], m.nu
limited = m.actuator_ctrllimited.astype(bool)
low, high = -jnp.ones(nu), jnp.ones(nu)
low = jnp.where(limited, m.actuator_ctrlrange[:, 0], low).astype(jnp.float32)
high = jnp.where(limited, m.actuator_ctrlrange[:, 1], high).astype(jnp.float32)
step = jax.vmap(mjx.step, in_axes=(None, 0))
def batch(mx, d0, key, index):
    ctrl = jax.random.uniform(jax.random.fold_in(key, index), (nstep, nbatch, nu),
                              minval=low, maxval=high)
    d = jax.tree.map(lambda x: jnp.broadcast_to(x, (nbatch, *x.shape)), d0)
    def body(d, u):
        d = step(mx, d.replace(ctrl=u))
        state = jnp.concatenate([d.time[:, None], d.qpos, d.qvel, d.act], axis=1)
        return d, (state, d.sensordata)
    _, (state, sensordata) = jax.lax.scan(body, d, ctrl)
    return {"state": state.swapaxes(0, 1), "sensordata": sensordata.swapaxes(0, 1),
            "control": ctrl.swapaxes(0, 1)}
key = jax.random.key(SPEC["seed"])
jitted = jax.jit(batch)
with jax.default_matmul_precision("float32"):
    if hasattr(jitted, "trace"):
        lowered = jitted.trace(mx, d0, key, 0).lower()
    else:
        lowered = jitted.lower(mx, d0, key, 0)
    mark("trace")
    compiled = lowered.compile()
    mark("compile")
out = jax.block_until_ready(compiled(mx, d0, key, 0))
mark("first_sim")
first = {k: torch.from_dlpack(v) for k, v in out.items()}
mark("handoff")
handed_over(first)
'''

RAW_WARP = PRELUDE + r'''
import mujoco
import warp as wp
import mujoco_warp as mjw
mark("import_engine")
wp.init()
m = mujoco.MjModel.from_xml_path(SPEC["model"])
nworld, nstep, nu = SPEC["nbatch"], SPEC["nstep"], m.nu
with wp.ScopedDevice("cuda:0"):
    mw = mjw.put_model(m)
    mw.opt.warn_overflow = 0  # no printf from the kernels (as simloader)
    d = mjw.make_data(m, nworld=nworld)
device = torch.device("cuda", 0)
t = lambda a: wp.to_torch(a).reshape(nworld, -1)
ctrl, parts, sensordata = t(d.ctrl), [t(getattr(d, f)) for f in ("time", "qpos", "qvel", "act")], t(d.sensordata)
limited = torch.as_tensor(m.actuator_ctrllimited.astype(bool), device=device)
rng = torch.as_tensor(m.actuator_ctrlrange, dtype=torch.float32, device=device)
low = torch.where(limited, rng[:, 0], -1.0)
high = torch.where(limited, rng[:, 1], 1.0)
stream = torch.cuda.Stream(device)
warp_stream = wp.stream_from_torch(stream)
torch.cuda.synchronize()
mark("construct")
with torch.cuda.stream(stream), wp.ScopedStream(warp_stream):
    mjw.step(mw, d)  # builds (or loads from the kernel cache) Warp's modules
    wp.synchronize_stream(warp_stream)
    mark("compile")
    with wp.ScopedCapture() as capture:
        mjw.step(mw, d)
    graph = capture.graph
    wp.synchronize_stream(warp_stream)
    mark("trace")
    mjw.reset_data(mw, d)  # back to the initial state after the two steps above
    gen = torch.Generator(device).manual_seed(SPEC["seed"])
    controls = low + (high - low) * torch.rand((nworld, nstep, nu), device=device, generator=gen)
    nstate = sum(p.shape[1] for p in parts)
    state = torch.empty((nworld, nstep, nstate), device=device)
    sensors = torch.empty((nworld, nstep, sensordata.shape[1]), device=device)
    for i in range(nstep):
        ctrl.copy_(controls[:, i])
        wp.capture_launch(graph, stream=warp_stream)
        torch.cat(parts, dim=1, out=state[:, i])
        sensors[:, i] = sensordata
stream.synchronize()
mark("first_sim")
first = {"state": state, "sensordata": sensors, "control": controls,
         "qpos": wp.to_torch(d.qpos)}  # the outputs are torch views of Warp's arrays already
torch.cuda.current_stream().wait_stream(stream)
torch.cuda.current_stream().synchronize()
mark("handoff")
handed_over(first)
'''

RAW_ROLLOUT = PRELUDE + r'''
import numpy as np
import mujoco
from mujoco import rollout
mark("import_engine")
m = mujoco.MjModel.from_xml_path(SPEC["model"])
try:
    nthread = len(os.sched_getaffinity(0))
except AttributeError:
    nthread = os.cpu_count() or 1
datas = [mujoco.MjData(m) for _ in range(nthread)]
full = mujoco.mjtState.mjSTATE_FULLPHYSICS
s0 = np.empty(mujoco.mj_stateSize(m, full))
mujoco.mj_getState(m, datas[0], s0, full)
nbatch, nstep = SPEC["nbatch"], SPEC["nstep"]
x0 = np.tile(s0, (nbatch, 1))
limited = m.actuator_ctrllimited.astype(bool)
low, high = -np.ones(m.nu), np.ones(m.nu)
low[limited] = m.actuator_ctrlrange[limited, 0]
high[limited] = m.actuator_ctrlrange[limited, 1]
rng = np.random.default_rng(SPEC["seed"])
mark("construct")
control = rng.uniform(low, high, size=(nbatch, nstep, m.nu))
state, sensordata = rollout.rollout(m, datas, x0, control, persistent_pool=True)
mark("first_sim")
first = {"state": torch.from_numpy(state), "sensordata": torch.from_numpy(sensordata),
         "control": torch.from_numpy(control)}
mark("handoff")
X["threads"] = nthread
handed_over(first)
'''

SIMLOADER = PRELUDE + r'''
import simloader
from simloader import controls
mark("import_engine")
kwargs = {"backend": SPEC["backend"], **SPEC.get("options", {})}
ds = simloader.SimDataset(SPEC["model"], nbatch=SPEC["nbatch"], nstep=SPEC["nstep"],
                          control=controls.Uniform(), seed=SPEC["seed"], **kwargs)
mark("construct")
it = iter(ds)
start = time.perf_counter()
batch = next(it)
first_s = time.perf_counter() - start
_LAST[0] = time.perf_counter()
if torch.cuda.is_available() and torch.cuda.is_initialized():
    # torch's stream only: a device-wide synchronize could break a CUDA graph capture of the
    # next batch under way in simloader's producer (see simloader.bench.sync)
    torch.cuda.current_stream().synchronize()
mark("handoff")
stats = ds.stats
stats = stats if isinstance(stats, dict) else dict(vars(stats))
trace, comp = stats.get("trace_s"), stats.get("compile_s")
P["trace"] = trace
P["compile"] = comp
P["first_sim"] = max(0.0, first_s - (trace or 0.0) - (comp or 0.0))
X.update({k: stats.get(k) for k in ("traces", "compiles", "programs_loaded", "backend",
                                      "graph_captures")})
handed_over(batch)
it.close()
'''

RAW_SCRIPT = {"mjx": RAW_JAX, "warp": RAW_WARP, "cpu": RAW_ROLLOUT}
SIM_OPTIONS = {"mjx": {"backend": "mjx"}, "warp": {"backend": "warp"},
               "cpu": {"backend": "cpu"}}


def profile_table(path: pathlib.Path, unit_s: float = 1e-6, top: int = 25) -> str:
    """A Markdown table of a child's sampled stacks (`run_child(profile=)`; folded lines,
    each stack's weight in `unit_s`): the `top` frames by inclusive seconds (the weight of
    the stacks the frame is on, once per stack where it recurses), each with its thread and
    self seconds (where it is the innermost frame). Import machinery's own frames
    (`<frozen importlib...>`) are left out of the table, not out of their callers' seconds."""
    inclusive: dict[tuple[str, str], int] = {}
    own: dict[tuple[str, str], int] = {}
    for line in path.read_text().splitlines():
        stack, _, weight = line.rpartition(" ")
        thread, *frames = stack.split(";")
        for frame in dict.fromkeys(frames):
            inclusive[thread, frame] = inclusive.get((thread, frame), 0) + int(weight)
        if frames:
            own[thread, frames[-1]] = own.get((thread, frames[-1]), 0) + int(weight)
    rows = sorted(((k, n) for k, n in inclusive.items() if not k[1].startswith("<frozen ")),
                  key=lambda kv: -kv[1])[:top]

    def cell(text: str) -> str:
        return "`" + text.replace("|", "\\|") + "`"
    lines = ["| thread | frame | inclusive s | self s |", "| --- | --- | --- | --- |"]
    lines += [f"| {cell(t)} | {cell(f)} | {n * unit_s:.3f} | {own.get((t, f), 0) * unit_s:.3f} |"
              for (t, f), n in rows]
    return "\n".join(lines)


def child_env(root: pathlib.Path, spec: dict, simloader: bool,
              isolate: bool = True) -> dict[str, str]:
    """The child's environment: its cache folders under `root` (`isolate`), else the user's."""
    env = dict(os.environ)
    for var, sub in (("XDG_CACHE_HOME", "xdg"), ("JAX_COMPILATION_CACHE_DIR", "jax"),
                     ("WARP_CACHE_PATH", "warp"), ("CUDA_CACHE_PATH", "cuda")):
        if isolate:
            env[var] = str(root / sub)
            (root / sub).mkdir(parents=True, exist_ok=True)
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    # bytecode caches on, as on a user's machine (an installed package's were compiled at
    # install): without them every child would compile the checkout's sources again (70 ms
    # for simloader's) while the raw scripts' libraries load theirs
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["BENCH_STARTUP_SPEC"] = json.dumps(spec)
    env["PYTHONPATH"] = pythonpath(env.get("PYTHONPATH", ""), checkout_first=simloader)
    return env


def pythonpath(given: str, checkout_first: bool = True) -> str:
    """`given` (a PYTHONPATH) with the checkout this package is in first, so that a child
    benchmarks this checkout, installed or not (`checkout_first=False`: taken out)."""
    paths = [p for p in given.split(os.pathsep) if p and pathlib.Path(p).resolve() != REPO]
    if checkout_first:
        paths.insert(0, str(REPO))
    return os.pathsep.join(paths)


def run_child(script: str, root: pathlib.Path, spec: dict, simloader: bool,
              timeout: float, isolate: bool = True,
              profile: Optional[pathlib.Path] = None) -> dict[str, Any]:
    """One fresh process in `root`; its JSON line, plus `wall`, or `{"error": ...}`.
    `profile`: a file the child writes its sampled stacks to (`PRELUDE`), from the end of
    `import torch` to the first batch."""
    env = child_env(root, spec, simloader, isolate)
    env.pop("BENCH_STARTUP_PROFILE", None)  # never the parent's: only a child asked samples
    if profile is not None:  # absolute: the child runs in `root`
        env["BENCH_STARTUP_PROFILE"] = str(pathlib.Path(profile).resolve())
    env["BENCH_STARTUP_T0"] = repr(time.time())
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                              env=env, cwd=root, timeout=timeout)
    except subprocess.TimeoutExpired as e:
        tail = (e.stderr or b"")[-1500:]
        tail = tail.decode(errors="replace") if isinstance(tail, bytes) else tail
        return {"error": f"timed out after {timeout:.0f} s\n{tail}"}
    wall = time.perf_counter() - start
    lines = [line for line in proc.stdout.strip().splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        return {"error": f"exit {proc.returncode}\n{proc.stderr[-3000:]}"}
    out = json.loads(lines[-1])
    out["wall"] = wall
    out["stderr"] = proc.stderr[-1500:]
    return out
