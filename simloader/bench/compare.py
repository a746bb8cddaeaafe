"""`simloader bench MODEL`: the engines that run here next to their raw simulators and a
Python loop, on one model and size, as a table and a bar chart.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Optional

import mujoco

from simloader.bench.raw import (PYTHON, RAW_OF, RAW_ROLLOUT, SIMLOADER_ROLLOUT, Workload,
                                 python_loop, raw_baseline, raw_rollout)
from simloader.bench.timing import (SimloaderMeasure, batches_for, cpu_count, device_name,
                                    interleave)


# -- tables and plots -------------------------------------------------------------------------

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


def bar_plot(path: str, title: str, s_per_step: dict[str, float]) -> None:
    """A horizontal bar chart of steps/s per method (log scale), raw baselines hatched."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(s_per_step)
    fig, ax = plt.subplots(figsize=(7, 0.6 * len(names) + 1.5))
    rates = [1 / s_per_step[n] for n in names]
    raw = [n in RAW_OF.values() or n == PYTHON for n in names]
    bars = ax.barh(names, rates, color=["lightgray" if r else "tab:blue" for r in raw],
                   edgecolor=["dimgray" if r else "tab:blue" for r in raw],
                   hatch=["//" if r else "" for r in raw])
    for value, bar in zip(rates, bars):
        ax.annotate(f" {value:,.3g}", (bar.get_width(), bar.get_y() + bar.get_height() / 2),
                    va="center")
    ax.set_xscale("log")
    # log-scale bars start at the left edge: put it well below the slowest, so lengths compare
    ax.set_xlim(min(rates) / 10, max(rates) * 3)
    ax.invert_yaxis()
    ax.set_xlabel("simulated steps per second (log)")
    ax.set_title(title)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# -- `simloader bench` ------------------------------------------------------------------------

def compare(model: mujoco.MjModel, w: Workload, backends: Sequence[str], *, repeats: int = 3,
            min_batches: int = 3, min_seconds: float = 2.0, python_steps: int = 5000,
            seed: int = 0) -> tuple[dict[str, float], dict[str, str], list[str]]:
    """Measures the chosen backends next to their raw simulators and a Python loop.

    Returns:
      (seconds per step of each method, where each runs, notes).
    """
    measures: dict[str, Callable[[], float]] = {}
    runs_on = {PYTHON: "1 core"}
    notes = []
    for backend in backends:
        if backend == "cpu":
            raw, batch_s = raw_rollout(model, w, cpu_count(), seed)
            # all the cores, as the raw rollout: nothing trains beside this measurement
            sim = SimloaderMeasure(model, w, "cpu", seed, nthread=cpu_count())
            n = batches_for(batch_s, min_batches, min_seconds)
            measures[RAW_ROLLOUT] = lambda raw=raw, n=n: raw(n)
            measures[SIMLOADER_ROLLOUT] = lambda sim=sim, n=n: sim.measure(n)
            runs_on[RAW_ROLLOUT] = runs_on[SIMLOADER_ROLLOUT] = f"{cpu_count()} cores"
        elif backend in ("mjx", "warp"):
            sim = SimloaderMeasure(model, w, backend, seed)
            Raw = raw_baseline(backend)
            raw = Raw.matching(model, w, seed, sim.ds.config.options)
            notes.append(f"{backend}: raw: {Raw.engine}")
            n = batches_for(raw.batch_s, min_batches, min_seconds)
            measures[Raw.row] = lambda raw=raw, n=n: raw.measure(n)
            measures[Raw.simloader_row] = lambda sim=sim, n=n: sim.measure(n)
            runs_on[Raw.row] = runs_on[Raw.simloader_row] = device_name(sim.device)
            notes.append(f"{backend}: compiled in {raw.compile_s:.1f} s (raw) and "
                         f"{sim.compile_s:.1f} s (simloader, first batch after "
                         f"{sim.first_s:.1f} s)")
        else:
            raise ValueError(f"backends: expected 'cpu', 'mjx' or 'warp', got {backend!r}")
    measures[PYTHON] = python_loop(model, w.nstep, python_steps, seed)
    return interleave(measures, repeats, desc=f"{w} x{repeats}"), runs_on, notes
