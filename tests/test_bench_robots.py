"""benchmarks/bench_robots.py: which engine each robot gets, and the table its JSON lines make.

The figures come from running it on a GPU (benchmarks/results/robots-*), never from a test; here
the engines' verdicts on real Menagerie models and the rendering of lines into rows.
"""

from __future__ import annotations

import datetime
import json
import pathlib
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import bench_robots  # noqa: E402

from simloader.bench.raw import RawMjx  # noqa: E402


def test_the_robots_are_the_menagerie_scenes_the_tests_carry():
    names = bench_robots.robots()
    assert len(names) >= 8 and "unitree_go1" in names and "universal_robots_ur5e" in names


def test_an_engine_that_refuses_a_robot_says_why_by_geom():
    assert bench_robots.refusal("universal_robots_ur5e", "mjx") is None
    why = bench_robots.refusal("unitree_go1", "mjx")
    assert why.startswith("refuses: MJX does not simulate frictionless contacts") and "geom" in why


def _first(robot, who, kind, total, after):
    return {"phase": "first", "robot": robot, "engine": "mjx", "who": who, "kind": kind,
            "total": total, "after_torch": after}


def test_the_table_holds_each_robot_to_the_raw_engine():
    lines = [
        {"phase": "machine", "GPU": "H200"},
        {"phase": "refused", "robot": "unitree_go1", "engine": "mjx", "refused": "refuses: X"},
        _first("ur5e", "raw", "cold", 30.0, 26.0), _first("ur5e", "simloader", "cold", 31.0, 27.5),
        _first("ur5e", "raw", "warm", 8.0, 4.0), _first("ur5e", "simloader", "warm", 8.5, 4.25),
        {"phase": "steady", "robot": "ur5e", "engine": "mjx",
         "s_per_step": {RawMjx.row: 1e-6, RawMjx.simloader_row: 1.1e-6}},
    ]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]]
            for line in bench_robots.table(lines).splitlines()[2:]}
    go1, ur5e = rows["unitree_go1"], rows["ur5e"]
    assert go1[2] == "refuses: X" and set(go1[3:]) == {"-"}
    assert ur5e[3:7] == ["31.0 / 30.0", "+1.50", "8.5 / 8.0", "+0.25"]
    assert ur5e[7:] == ["0.91M", "1.00M", "0.909 (**no**)"]  # 1/1.1 of raw, below 0.97


def test_report_renders_the_lines_already_written_and_nothing_else(tmp_path):
    today = datetime.date.today().isoformat()  # the script names its files by the date
    lines = tmp_path / f"robots-t-{today}.jsonl"
    lines.write_text("\n".join(json.dumps(x) for x in [
        {"phase": "machine", "GPU": "NVIDIA H200"},
        _first("ur5e", "raw", "warm", 8.0, 4.0), _first("ur5e", "simloader", "warm", 8.5, 4.25),
    ]) + "\n")
    mine = tmp_path / "mine.txt"
    mine.write_text("the user's")
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_robots.py"), "--phase",
                    "report", "--tag", "t", "--results-dir", str(tmp_path), "--save",
                    "--note", "a note"], check=True, capture_output=True, text=True, cwd=REPO)
    md = (tmp_path / f"robots-t-{today}.md").read_text()
    assert md.startswith("# Menagerie robots on the GPU engines")
    assert "GPU: NVIDIA H200" in md and "a note" in md and "8.5 / 8.0" in md
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "mine.txt", f"robots-t-{today}.jsonl", f"robots-t-{today}.md", f"robots-t-{today}.png"]
    assert f"![steps/s against the raw engine, first batches](robots-t-{today}.png)" in md
    assert (tmp_path / f"robots-t-{today}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert mine.read_text() == "the user's"


def test_a_first_phase_refuses_a_cache_root_that_exists(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_robots.py"),
                           "--engines", "mjx", "--robots", "universal_robots_ur5e",
                           "--cache-root", str(tmp_path), "--results-dir", str(tmp_path)],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode != 0 and "--cache-root" in proc.stderr and "exists" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_steady_phase_without_the_first_phases_caches_is_refused(tmp_path):
    # its children would compile every robot cold: minutes each of a GPU machine's time
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_robots.py"),
                           "--phase", "steady", "--cache-root", str(tmp_path / "none"),
                           "--lines", str(tmp_path / "lines.jsonl")],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode != 0 and "--cache-root" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_run_without_save_writes_nothing_into_the_results_folder(tmp_path):
    # MJX refuses the Go1 (condim 1 under the elliptic cone): no child runs, the table is
    # printed, and its JSON lines go to a temporary file, not into --results-dir
    results = tmp_path / "results"
    results.mkdir()
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "bench_robots.py"),
                           "--engines", "mjx", "--robots", "unitree_go1", "--phase", "first",
                           "--cache-root", str(tmp_path / "caches"),
                           "--results-dir", str(results)],
                          capture_output=True, text=True, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "refuses" in proc.stdout and "not kept in the results folder" in proc.stderr
    assert list(results.iterdir()) == []


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
