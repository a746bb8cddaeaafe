"""The start-up children's sampled stacks (`run_child(profile=)`, `bench_startup.py --profile`):
every thread's frames from the end of `import torch` to the first batch, per side."""

from __future__ import annotations

import pathlib

from simloader.bench import startup

MODEL = str(pathlib.Path(__file__).resolve().parents[1] / "simloader" / "assets" / "cartpole.xml")


def test_profile_table_counts_inclusive_once_per_sample_and_self_at_the_leaf(tmp_path):
    folded = tmp_path / "x.folded"
    folded.write_text("MainThread;a.py:f;b.py:g;a.py:f 3\n"   # f recursive: once per sample
                      "MainThread;a.py:f 2\n"
                      "worker;c.py:h 5\n")
    table = startup.profile_table(folded, every_s=0.01)
    rows = {line.split("|")[2].strip(): line for line in table.splitlines()[2:]}
    assert "| MainThread | `a.py:f` | 0.050 | 0.050 |" in table  # 5 samples, 3 + 2 at the leaf
    assert "| MainThread | `b.py:g` | 0.030 | 0.000 |" in table
    assert "| worker | `c.py:h` | 0.050 | 0.050 |" in table
    assert len(rows) == 3


def test_a_child_writes_the_stacks_of_its_threads_only_when_asked(tmp_path):
    spec = {"model": MODEL, "nbatch": 64, "nstep": 50, "seed": 0, "backend": "cpu"}
    (tmp_path / "simloader").mkdir()
    folded = tmp_path / "simloader.folded"
    line = startup.run_child(startup.SIMLOADER, tmp_path / "simloader", spec, simloader=True,
                             timeout=300, profile=folded)
    assert "error" not in line, line
    assert line["extra"]["profile"]["file"] == folded.name
    assert line["extra"]["profile"]["samples"] > 0
    stacks = folded.read_text()
    # the dataset built on the main thread, its first batch made on the prefetch thread
    # (which a profile of the main thread alone would miss), MuJoCo's rollout under it
    assert "MainThread;" in stacks and "simloader/dataset.py:__init__" in stacks
    assert any(s.startswith("simloader-prefetch;") and "rollout" in s
               for s in stacks.splitlines())
    table = startup.profile_table(folded, line["extra"]["profile"]["every_s"])
    assert table.startswith("| thread | frame | inclusive s | self s |")
    # without profile=: no sampler, no file, no profile in the line
    (tmp_path / "raw").mkdir()
    line = startup.run_child(startup.RAW_ROLLOUT, tmp_path / "raw", spec, simloader=False,
                             timeout=300)
    assert "error" not in line, line
    assert "profile" not in line["extra"]
    assert sorted(p.name for p in tmp_path.glob("*.folded")) == ["simloader.folded"]
