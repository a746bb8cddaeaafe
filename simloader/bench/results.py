"""The suite's results as data: one JSON line per (workload, side, machine, commit, date), and
what `simloader bench report` renders from them (a Markdown table and a plot of the ratios
against their targets), which the Speed page and the README cite.
"""

from __future__ import annotations

import json
import os
import pathlib
from collections.abc import Iterable, Sequence
from typing import Any, Optional


def append_lines(path: pathlib.Path, lines: Iterable[dict[str, Any]]) -> None:
    """Appends `lines` to the JSON-lines file `path` (created with its folder when needed),
    flushed and synced, so that a run cut short keeps every finished workload."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a", encoding="utf-8") as f:
        for line in lines:
            f.write(json.dumps(line, sort_keys=True) + "\n")
        f.flush()
        os.fsync(f.fileno())


def read_lines(paths: Sequence[os.PathLike | str]) -> list[dict[str, Any]]:
    """Every line of the JSON-lines files, in order.

    Raises:
      ValueError: a line is not a JSON object (naming the file and line).
    """
    out = []
    for path in paths:
        with open(path, encoding="utf-8") as f:
            for number, text in enumerate(f, 1):
                if not text.strip():
                    continue
                try:
                    line = json.loads(text)
                except json.JSONDecodeError as e:
                    raise ValueError(f"{path}:{number}: expected a JSON object per line ({e})") \
                        from None
                if not isinstance(line, dict):
                    raise ValueError(f"{path}:{number}: expected a JSON object, got "
                                     f"{type(line).__name__}")
                out.append(line)
    return out


def latest(lines: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The last subject line of each workload, with its baseline's last line attached
    (`baseline`), in first-seen order: a rerun of a workload replaces its row in place."""
    rows: dict[str, dict[str, Any]] = {}
    baselines: dict[str, dict[str, Any]] = {}
    for line in lines:
        name = line.get("workload")
        if line.get("role") == "baseline":
            baselines[name] = line
        elif line.get("role") == "subject":
            if "skipped" in line and name in rows and "skipped" not in rows[name]:
                continue  # a machine with too few GPUs says nothing about a measured row
            rows[name] = line  # a dict keeps the key's first position
    return [{**row, "baseline": None if "error" in row or "skipped" in row
             else baselines.get(name)}
            for name, row in rows.items()]


def failures(lines: Sequence[dict[str, Any]]) -> list[str]:
    """One sentence per workload below its target (or failed), naming it: what `--check`
    prints before exiting non-zero."""
    out = []
    for row in latest(lines):
        if row.get("passed") is not False:
            continue
        if "error" in row:
            out.append(f"{row['workload']}: failed: {row['error']}")
            continue
        what = f"{row['workload']}: {ratio_text(row)}x its baseline"
        if row.get("target") is not None:
            what += f", target {row['target']:.3f}x"
        after = (row.get("extra") or {}).get("after_torch_s")
        if row.get("ceiling_s") is not None and after is not None:
            what += f"; first batch {after:.2f} s after torch's import, ceiling " \
                    f"{row['ceiling_s']:.2f} s"
        out.append(what)
    return out


def ratio_text(row: dict[str, Any]) -> str:
    """A row's ratio to 3 decimals, or more where 3 would read as its target or above it
    (0.9497 against 0.95 is below it; "0.950" would not say so)."""
    ratio, target = row["ratio"], row.get("target")
    digits = 3
    while (target is not None and ratio < target and digits < 8
           and float(f"{ratio:.{digits}f}") >= target):
        digits += 1
    return f"{ratio:.{digits}f}"


def _rate(x: Optional[float], unit: str) -> str:
    if x is None:
        return "-"
    if unit == "first batches":
        return f"{1 / x:.2f} s"
    return f"{x / 1e6:,.2f}M" if x >= 1e5 else f"{x:,.0f}"


def _verdict(row: dict[str, Any]) -> str:
    if "error" in row:
        return "failed"
    if "skipped" in row:
        return f"skipped: {row['skipped']}"
    if row.get("target") is None:
        return "measured"
    return "yes" if row.get("passed") else "**no**"


def table(lines: Sequence[dict[str, Any]]) -> str:
    """The Markdown table of the latest row of each workload."""
    from simloader.bench.compare import markdown_table
    rows = []
    for row in latest(lines):
        unit = row.get("unit", "steps")
        base = row.get("baseline") or {}
        kind, _, stream = row.get("method", "").partition(": ")
        base_kind, _, base_stream = base.get("method", "").partition(": ")
        per = {"steps": "steps/s", "frames": "frames/s"}.get(unit, f"{unit}/s")
        failed = "error" in row or "skipped" in row
        rows.append([
            row["workload"], "-" if failed else stream,
            "-" if failed else f"{kind} / {base_kind}" + (
                "" if base_stream == stream else f" ({base_stream})"),
            "-" if failed else (f"{_rate(row.get('units_per_s'), unit)} to the first batch"
                                if unit == "first batches"
                                else f"{_rate(row.get('units_per_s'), unit)} {per}"),
            _rate(base.get("units_per_s"), unit) if base else "-",
            ratio_text(row) if row.get("ratio") is not None else "-",
            f">= {row['target']:.3g}" if row.get("target") is not None else "-",
            _verdict(row)])
    return markdown_table(["workload", "stream", "subject / baseline", "subject", "baseline",
                           "ratio", "target", "holds"], rows)


def header(lines: Sequence[dict[str, Any]]) -> str:
    """Where and when: machine, dates, commits, versions of the lines."""
    if not lines:
        return "No results."
    dates = sorted(line["date"] for line in lines if "date" in line)
    commits = sorted({f"{(line.get('commit') or 'unknown')[:10]}"
                      f"{' (tracked files changed)' if line.get('dirty') else ''}"
                      for line in lines})
    machines = sorted({json.dumps(line.get("machine"), sort_keys=True) for line in lines})
    first = next((line for line in lines if "versions" in line), {})
    versions = ", ".join(f"{k} {v}" for k, v in (first.get("versions") or {}).items() if v)
    m = [json.loads(x) for x in machines]
    where = "; ".join(f"{x['device']} ({x['gpus']} GPU, {x['cpus']} cores, "
                      f"{x['memory_gib']} GiB)" if x.get("gpus") else
                      f"{x['device']} ({x['cpus']} cores, {x['memory_gib']} GiB)"
                      for x in m if x)
    return (f"Machine: {where}. Dates: {dates[0]} to {dates[-1]}. Commit: "
            f"{', '.join(commits)}. Versions: {versions}.")


def plot(lines: Sequence[dict[str, Any]], path: os.PathLike | str, title: str) -> None:
    """Horizontal bars of each workload's ratio, its target marked; misses in red."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in latest(lines) if r.get("ratio") is not None]
    fig, ax = plt.subplots(figsize=(8, 0.32 * len(rows) + 1.4))
    names = [r["workload"] for r in rows]
    ratios = [r["ratio"] for r in rows]
    colors = ["lightgray" if r.get("target") is None else
              ("tab:blue" if r.get("passed") else "tab:red") for r in rows]
    ax.barh(names, ratios, color=colors)
    for y, r in enumerate(rows):
        if r.get("target") is not None:
            ax.plot([r["target"]] * 2, [y - 0.4, y + 0.4], color="black", lw=1.5)
        ax.annotate(f" {ratio_text(r)}", (r["ratio"], y), va="center", fontsize=8)
    ax.axvline(1.0, color="gray", lw=0.8, ls=":")
    ax.invert_yaxis()
    ax.set_xlim(0, max([1.2] + [x * 1.15 for x in ratios]))
    ax.set_xlabel("simloader / baseline (tick: target; gray: measured only)")
    ax.set_title(title)
    ax.tick_params(axis="y", labelsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(lines: Sequence[dict[str, Any]], out: pathlib.Path, name: str,
           title: str, notes: Sequence[str] = ()) -> tuple[pathlib.Path, pathlib.Path]:
    """Writes `out/name.md` (title, where and when, `notes`, the table, misses) and
    `out/name.png`."""
    out.mkdir(parents=True, exist_ok=True)
    md, png = out / f"{name}.md", out / f"{name}.png"
    missed = failures(lines)
    text = [f"# {title}", "", header(lines), "", *[f"{n}\n" for n in notes],
            "Medians of alternating repetitions in one process; ratio = simloader's throughput "
            "over the baseline's (for start-up, the baseline's seconds over simloader's). "
            f"Rendered by `simloader bench report` from the JSON lines `{name}.jsonl`.", "",
            table(lines), ""]
    if missed:
        text += ["Below target:", ""] + [f"- {m}" for m in missed] + [""]
    md.write_text("\n".join(text), encoding="utf-8")
    plot(lines, png, title)
    return md, png
