"""The start-up children's sampled stacks (`run_child(profile=)`, `bench_startup.py --profile`):
every thread's frames from the end of `import torch` to the first batch, per side."""

from __future__ import annotations

import pathlib

from simloader.bench import startup

MODEL = str(pathlib.Path(__file__).resolve().parents[1] / "simloader" / "assets" / "cartpole.xml")


def test_profile_table_weighs_inclusive_once_per_stack_and_self_at_the_leaf(tmp_path):
    folded = tmp_path / "x.folded"
    folded.write_text("MainThread;a.py:f;b.py:g;a.py:f 3000\n"  # f recursive: once per stack
                      "MainThread;a.py:f 2000\n"
                      "MainThread;<frozen importlib._bootstrap>:_load;c.py:<module> 1000\n"
                      "Thread-1 (work|er);c.py:h 5000\n")
    table = startup.profile_table(folded, unit_s=1e-6)
    assert "| `MainThread` | `a.py:f` | 0.005 | 0.005 |" in table  # innermost in both stacks
    assert "| `MainThread` | `b.py:g` | 0.003 | 0.000 |" in table
    assert "| `MainThread` | `c.py:<module>` | 0.001 | 0.001 |" in table
    assert "| `Thread-1 (work\\|er)` | `c.py:h` | 0.005 | 0.005 |" in table  # | escaped
    assert "frozen" not in table  # the import machinery's frames: out of the table
    assert len(table.splitlines()) == 2 + 4


def test_a_child_writes_the_stacks_of_its_threads_only_when_asked(tmp_path, monkeypatch):
    spec = {"model": MODEL, "nbatch": 64, "nstep": 50, "seed": 0, "backend": "cpu"}
    (tmp_path / "simloader").mkdir()
    monkeypatch.chdir(tmp_path)
    line = startup.run_child(startup.SIMLOADER, tmp_path / "simloader", spec, simloader=True,
                             timeout=300, profile=pathlib.Path("simloader.folded"))
    # a relative path is the caller's, not the child's (which runs in its cache folder)
    folded = tmp_path / "simloader.folded"
    assert "error" not in line, line
    assert line["extra"]["profile"]["file"] == folded.name
    stacks = folded.read_text()
    weights = [int(s.rpartition(" ")[2]) for s in stacks.splitlines()]
    # weighted by time: the main thread's stacks add up to most of its seconds after torch
    main = sum(w for s, w in zip(stacks.splitlines(), weights) if s.startswith("MainThread;"))
    assert 0.5 * line["after_torch"] < main * 1e-6 <= 1.05 * line["after_torch"]
    # the dataset built on the main thread, its first batch made on the prefetch thread
    # (which a profile of the main thread alone would miss), MuJoCo's rollout under it
    assert "simloader/dataset.py:SimDataset.__init__" in stacks
    assert any(s.startswith("simloader-prefetch;") and "rollout" in s
               for s in stacks.splitlines())
    table = startup.profile_table(folded, line["extra"]["profile"]["unit_s"])
    assert table.startswith("| thread | frame | inclusive s | self s |")
    # without profile=: no sampler, no file, no profile in the line, even where the parent's
    # environment names one
    monkeypatch.setenv("BENCH_STARTUP_PROFILE", str(tmp_path / "leaked.folded"))
    (tmp_path / "raw").mkdir()
    line = startup.run_child(startup.RAW_ROLLOUT, tmp_path / "raw", spec, simloader=False,
                             timeout=300)
    assert "error" not in line, line
    assert "profile" not in line["extra"]
    assert sorted(p.name for p in tmp_path.glob("*.folded")) == ["simloader.folded"]
