"""What the benchmark scripts share: workloads, models, timing, tables, result files, plots.

The scripts are run as files from the repository root (`python benchmarks/bench_rollout.py`),
which puts this folder on `sys.path`. Timing follows `shared/design/performance.md`: steady
state after a warm-up, blocked on results, repeated, medians; simloader and the raw simulator
are measured in the same process, alternating repetitions.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib.metadata
import json
import math
import os
import pathlib
import platform
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Optional

import mujoco
import numpy as np
import torch

REPO = pathlib.Path(__file__).resolve().parent.parent
# benchmark the checkout the scripts are in, installed or not
sys.path.insert(0, str(REPO))
# the lead copies the models into the ignored .models/ (only the repository travels to the GPU
# machine); a developer checkout has them in ../shared
MODEL_DIRS = (REPO / ".models" / "dm_control", REPO.parent / "shared" / "models" / "dm_control")


@dataclasses.dataclass(frozen=True)
class Workload:
    """`nbatch` trajectories of `nstep` steps of the model `name` (a file `<name>.xml`)."""

    name: str
    nbatch: int
    nstep: int

    @property
    def steps(self) -> int:
        return self.nbatch * self.nstep

    def __str__(self) -> str:
        return f"{self.name}:{self.nbatch}x{self.nstep}"


def parse_workload(text: str) -> Workload:
    """`cartpole:8192x1000` -> Workload("cartpole", 8192, 1000) (for argparse)."""
    try:
        name, sizes = text.split(":")
        nbatch, nstep = sizes.lower().split("x")
        return Workload(name, int(nbatch), int(nstep))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a workload MODEL:NBATCHxNSTEP such as cartpole:8192x1000, got {text!r}"
        ) from None


def parser(description: str, workloads: Sequence[Workload], quick: Sequence[Workload],
           throughput: bool = False, repeats: bool = True) -> argparse.ArgumentParser:
    """An argument parser with the options every script takes (`throughput`: and those of
    the throughput benchmarks; `parse` fills in their defaults; `repeats`: --repeats, for
    scripts that time repeated measurements)."""
    p = argparse.ArgumentParser(description=description,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help=f"tiny sizes for a smoke run on a laptop ({', '.join(map(str, quick))})")
    p.add_argument("--workloads", nargs="+", type=parse_workload, metavar="MODEL:NBATCHxNSTEP",
                   help=f"what to run (default: {' '.join(map(str, workloads))})")
    p.add_argument("--model-dir", type=pathlib.Path,
                   help=f"folder of the MJCF files (default: the first of "
                        f"{', '.join(str(d) for d in MODEL_DIRS)} that exists)")
    if repeats:
        p.add_argument("--repeats", type=int, default=3,
                       help="timed repetitions of each measurement (the median is reported)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", action="store_true",
                   help="write the table, the environment and the command line (and any plot) "
                        "to RESULTS_DIR/<script>-<date>.md")
    p.add_argument("--results-dir", type=pathlib.Path, default=REPO / "benchmarks" / "results",
                   help="where --save writes (on the GPU machine: $OUT)")
    p.add_argument("--tag", default="", help="suffix of the saved file names")
    if throughput:
        p.add_argument("--batches", type=int,
                       help="timed batches per repetition, at least (default 4, --quick 3)")
        p.add_argument("--min-seconds", type=float,
                       help="more batches where a batch is quick, so that each timed run lasts "
                            "this long at least (default 2, --quick 0)")
        p.add_argument("--python-steps", type=int,
                       help="steps of the Python loop per repetition (default 10000, --quick "
                            "1000)")
    return p


def parse(p: argparse.ArgumentParser) -> argparse.Namespace:
    """Parses the command line; throughput options left out get their (--quick) defaults."""
    args = p.parse_args()
    for name, default, quick in (("batches", 4, 3), ("min_seconds", 2.0, 0.0),
                                 ("python_steps", 10000, 1000)):
        if getattr(args, name, 0) is None:
            setattr(args, name, quick if args.quick else default)
    return args


def batches_for(args: argparse.Namespace, batch_s: float) -> int:
    """Timed batches per repetition: `--batches`, or more to last `--min-seconds`."""
    return max(args.batches, math.ceil(args.min_seconds / batch_s))


def workloads(args: argparse.Namespace, default: Sequence[Workload],
              quick: Sequence[Workload]) -> list[Workload]:
    """The workloads asked for: --workloads, else the --quick ones, else the defaults."""
    return list(args.workloads or (quick if args.quick else default))


def model_dir(given: Optional[pathlib.Path]) -> pathlib.Path:
    if given is not None:
        if not given.is_dir():
            raise SystemExit(f"--model-dir: {given} is not a folder")
        return given
    for d in MODEL_DIRS:
        if d.is_dir():
            return d
    raise SystemExit(f"no model folder found (looked in {', '.join(map(str, MODEL_DIRS))}); "
                     f"pass --model-dir")


def load_model(name: str, folder: Optional[pathlib.Path]) -> mujoco.MjModel:
    """The MjModel of `<folder>/<name>.xml`."""
    path = model_dir(folder) / f"{name}.xml"
    if not path.is_file():
        raise SystemExit(f"model {name!r}: no file {path}")
    return mujoco.MjModel.from_xml_path(str(path))


def ctrl_bounds(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Per-actuator (low, high) of uniform controls: `ctrlrange` if limited, else [-1, 1].

    Written out here rather than taken from simloader, so that the raw baselines depend on
    MuJoCo alone; it is the default range of `simloader.controls.Uniform()`.
    """
    limited = model.actuator_ctrllimited.astype(bool)
    low, high = -np.ones(model.nu), np.ones(model.nu)
    low[limited] = model.actuator_ctrlrange[limited, 0]
    high[limited] = model.actuator_ctrlrange[limited, 1]
    return low, high


def cpu_count() -> int:
    """CPU cores this process may run on (what simloader's rollout backend uses)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def run_child(command: Sequence[str], what: str,
              env: Optional[dict[str, str]] = None) -> Optional[dict[str, Any]]:
    """Runs a fresh process (a script's own child mode) and returns the JSON object on the
    last line of its stdout; None, with the end of its stderr shown, if it failed."""
    proc = subprocess.run(list(command), capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        print(f"{what} failed:\n{proc.stderr[-3000:]}", file=sys.stderr)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- timing -----------------------------------------------------------------------------------

def sync() -> None:
    """Waits for all queued GPU work (every stream of the device: torch's and JAX's)."""
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def drain() -> None:
    """Waits until the work already dispatched to the devices has run.

    simloader's MJX producer dispatches batches ahead; those an iterator was closed on still
    run on the device and would slow whatever is timed next. Devices run their work in order,
    so a tiny computation on each, waited for, waits for them.
    """
    sync()
    jax = sys.modules.get("jax")
    if jax is not None:
        for device in jax.local_devices():
            jax.block_until_ready(jax.device_put(0, device) + 1)


def interleave(measures: dict[str, Callable[[], float]], repeats: int,
               desc: str = "") -> dict[str, float]:
    """The median of each measure's result, the measures run alternately `repeats` times.

    Each measure times its own steady part (warm-up excluded) and returns seconds per
    simulated step. The order is
    reversed every repetition, so that drift in the machine (clocks, caches, other load)
    touches every measure alike.
    """
    times: dict[str, list[float]] = {name: [] for name in measures}
    order = list(measures)
    for rep in progress(range(repeats), desc=desc):
        for name in order if rep % 2 == 0 else reversed(order):
            times[name].append(measures[name]())
    return {name: statistics.median(t) for name, t in times.items()}


@dataclasses.dataclass
class Stream:
    """One pass over a dataset: `first_s` to the first batch, `steady_s` for the rest."""

    first_s: float
    steady_s: float
    last: Optional[dict[str, torch.Tensor]] = None


def time_stream(ds: Iterable[dict[str, torch.Tensor]], nbatches: int,
                keep_last: bool = False) -> Stream:
    """Delivered throughput of a dataset: `nbatches` batches after the first, tensors in hand.

    A fresh iterator per call: simloader's producer thread starts with it and stops at
    `close`, and the device is drained, so nothing simulates while another measure runs. The
    first batch, which pays for threads, compilation and the empty prefetch queue, is timed
    apart; the steady part runs from holding the first batch to holding the last, blocked on
    the device after each.
    """
    it = iter(ds)
    try:
        start = time.perf_counter()
        batch = next(it)
        sync()
        first = time.perf_counter()
        for _ in range(nbatches):
            del batch  # release a (possibly multi-GB) batch before the next arrives
            batch = next(it)
            sync()
        return Stream(first - start, time.perf_counter() - first, batch if keep_last else None)
    finally:
        it.close()
        drain()


# -- output -----------------------------------------------------------------------------------

def ns(seconds_per_step: float) -> str:
    return f"{seconds_per_step * 1e9:,.1f}" if seconds_per_step < 1e-7 else \
        f"{seconds_per_step * 1e9:,.0f}"


def rate(steps_per_second: float) -> str:
    return f"{steps_per_second / 1e6:,.2f}M"


def ratio(x: Optional[float]) -> str:
    return "-" if x is None else f"{x:.3f}"


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table, columns padded for reading in a terminal too."""
    cells = [list(map(str, headers))] + [list(map(str, r)) for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    line = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([line(cells[0]), "| " + " | ".join("-" * w for w in widths) + " |"]
                     + [line(r) for r in cells[1:]])


HEADERS = ["workload", "nbatch x nstep", "method", "runs on", "ns/step", "steps/s",
           "throughput / raw", "vs Python loop"]


def method_rows(w: Workload, s_per_step: dict[str, float], runs_on: dict[str, str],
                raw_of: dict[str, str], python: Optional[str]) -> list[list[str]]:
    """Rows of `HEADERS`, one per method, in the order of `s_per_step`.

    Args:
      s_per_step: seconds per simulated step of each method.
      runs_on: where each method runs ("16 cores", "NVIDIA H200").
      raw_of: for a simloader method, the raw method it is compared to (throughput ratio).
      python: the method that is the single-environment Python loop, for speed-ups.
    """
    base = s_per_step.get(python)
    rows = []
    for method, s in s_per_step.items():
        raw = s_per_step.get(raw_of.get(method, method)) if method in raw_of or \
            method in raw_of.values() else None
        rows.append([w.name, f"{w.nbatch} x {w.nstep}", method, runs_on[method], ns(s),
                     rate(1 / s), ratio(raw / s if raw else None),
                     f"{base / s:,.1f}x" if base else "-"])
    return rows


def progress(iterable: Iterable, desc: str = "", total: Optional[int] = None) -> Iterable:
    """A tqdm progress bar on stderr, or the bare iterable where tqdm is not installed."""
    try:
        from tqdm import tqdm
    except ImportError:  # the GPU machine has only what its carried wheels install
        return iterable
    return tqdm(iterable, desc=desc, total=total, leave=False, file=sys.stderr,
                mininterval=1.0 if sys.stderr.isatty() else 30.0)


def _version(package: str) -> str:
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        return "not installed"


def _simloader_version() -> str:
    import simloader  # the checkout's (see the sys.path line above)
    return simloader.__version__


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"],
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _cpu_name() -> str:
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def environment() -> dict[str, str]:
    """Date, device, versions and command line, for the record of a result."""
    gpu = (", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
           if torch.cuda.is_available() else "none")
    return {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "GPU": gpu,
        "CPU": f"{cpu_count()} cores usable ({_cpu_name()})",
        "python": platform.python_version(),
        "mujoco": _version("mujoco"),
        "mujoco-mjx": _version("mujoco-mjx"),
        "jax": f"{_version('jax')} (jaxlib {_version('jaxlib')})",
        "torch": torch.__version__,
        "numpy": _version("numpy"),
        "simloader": f"{_simloader_version()} (commit {_git_commit()})",
        "command": shlex.join(["python", *sys.argv]),
    }


def result_path(args: argparse.Namespace, name: str, suffix: str) -> pathlib.Path:
    date = datetime.date.today().isoformat()
    tag = f"-{args.tag}" if args.tag else ""
    return args.results_dir / f"{name}{tag}-{date}{suffix}"


def save(args: argparse.Namespace, name: str, title: str, sections: Sequence[str]) -> pathlib.Path:
    """Writes `sections` (Markdown) under a header of environment facts; returns the path."""
    env = environment()
    lines = [f"# {title}", ""] + [f"- {k}: `{v}`" if k == "command" else f"- {k}: {v}"
                                  for k, v in env.items()]
    path = result_path(args, name, ".md")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n\n" + "\n\n".join(sections) + "\n")
    print(f"saved {path}", file=sys.stderr)
    return path


def save_plot(args: argparse.Namespace, name: str, series: dict[str, tuple[list, list]],
              xlabel: str, ylabel: str, title: str, log: bool = True) -> Optional[pathlib.Path]:
    """A line plot of `{label: (x, y)}` (log-log unless `log` is False), saved as a PNG next
    to the results; raw baselines (labels with "raw") dashed."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot", file=sys.stderr)
        return None
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for label, (x, y) in series.items():
        ax.plot(x, y, marker="o", label=label, linestyle="--" if "raw" in label else "-")
    if log:
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path = result_path(args, name, ".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    print(f"saved {path}", file=sys.stderr)
    return path
