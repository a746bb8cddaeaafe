"""What the benchmark scripts share: workloads, models, timing, tables, result files, plots.

The scripts are run as files from the repository root (`python benchmarks/bench_rollout.py`),
which puts this folder on `sys.path`. Timing follows `shared/design/performance.md`: steady
state after a warm-up, blocked on results, repeated, medians; simloader and the raw simulator
are measured in the same process, alternating repetitions.
"""

from __future__ import annotations

import argparse
import datetime
import importlib.metadata
import json
import pathlib
import platform
import shlex
import subprocess
import sys
from collections.abc import Sequence
from typing import Any, Optional

import mujoco
import torch

REPO = pathlib.Path(__file__).resolve().parent.parent
# benchmark the checkout the scripts are in, installed or not
sys.path.insert(0, str(REPO))
# the measuring core is the package's (it backs `simloader bench`); re-exported for the scripts
from simloader.bench import (  # noqa: E402,F401
    HEADERS, Stream, Workload, cpu_count, ctrl_bounds, drain, interleave, markdown_table,
    method_rows, ns, progress, rate, ratio, sync, time_stream)
from simloader import bench as _bench  # noqa: E402
# the lead copies the models into the ignored .models/ (only the repository travels to the GPU
# machine); a developer checkout has them in ../shared
MODEL_DIRS = (REPO / ".models" / "dm_control", REPO.parent / "shared" / "models" / "dm_control")


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
    add_output_options(p)
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


def add_output_options(p: argparse.ArgumentParser) -> None:
    """--save, --results-dir and --tag: where and under which name results are written."""
    p.add_argument("--save", action="store_true",
                   help="write the table, the environment and the command line (and any plot) "
                        "to RESULTS_DIR/<script>[-TAG]-<date>.md")
    p.add_argument("--results-dir", type=pathlib.Path, default=REPO / "benchmarks" / "results",
                   help="where --save writes (on the GPU machine: $OUT)")
    p.add_argument("--tag", default="", help="suffix of the saved file names")


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
    return _bench.batches_for(batch_s, args.batches, args.min_seconds)


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


def run_child(command: Sequence[str], what: str,
              env: Optional[dict[str, str]] = None) -> Optional[dict[str, Any]]:
    """Runs a fresh process (a script's own child mode) and returns the JSON object on the
    last line of its stdout; None, with the end of its stderr shown, if it failed."""
    proc = subprocess.run(list(command), capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        print(f"{what} failed:\n{proc.stderr[-3000:]}", file=sys.stderr)
        return None
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- result files -----------------------------------------------------------------------------

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


def report(args: argparse.Namespace, name: str, title: str, sections: Sequence[str]) -> None:
    """Prints `sections` and, with --save, writes them as `save` does."""
    if args.save:
        save(args, name, title, sections)
    print("\n\n".join(sections))


def save_figure(args: argparse.Namespace, name: str, fig: Any) -> pathlib.Path:
    """Saves a matplotlib figure as a PNG next to the results and closes it."""
    import matplotlib.pyplot as plt
    path = result_path(args, name, ".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
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
    return save_figure(args, name, fig)
