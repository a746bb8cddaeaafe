"""`simloader bench run | report | list`: the suite's table builds real datasets, a run writes
its JSON lines and `--check` names a workload below its target, the lines render, and every
kind of side (raw, write, render on read, mixture) measures at tiny sizes on the CPU engine.
The figures themselves come from running the suite (benchmarks/results/), never from a test.
"""

import json
import math
import statistics

import pytest
import torch

import simloader
from simloader import cli
from simloader.bench import datasets, results, suite
from simloader.bench import workloads as W
from simloader.bench.workloads import Benchmark, Method, Stream

TINY = Stream("cartpole", "cpu", 8, 10)


def streams_of(b):
    return b.subject.streams + b.baseline.streams


@pytest.mark.parametrize("b", W.ALL, ids=lambda b: b.name)
def test_every_workload_is_a_dataset_the_engines_accept(b):
    # the rules, randomization and records of the table, parsed against the real models (a
    # typo'd joint or body fails here, not on the GPU machine); built on the CPU engine
    assert b.suite in W.SUITES and (b.target is None or 0 < b.target <= 1.5) and b.source
    for s in streams_of(b):
        model = simloader.load_model(s.model)
        small = s.but(engine="cpu", nbatch=2, nstep=3)
        simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=3,
                             **datasets.options(small, model))


def test_every_target_workload_names_its_baseline_and_both_suites_exist():
    names = [b.name for b in W.ALL]
    assert len(set(names)) == len(names)
    assert {b.suite for b in W.ALL} == set(W.SUITES)
    # the list: each target has a workload on the GPU
    gpu = {b.name for b in W.ALL if b.suite == "gpu"}
    for part in ("open-loop", "continued", "policy", "episodes", "camera", "randomize",
                 "record", "write", "render-on-read", "mixture", "startup"):
        assert any(part in n for n in gpu), part
    episodes = [b for b in W.ALL if b.suite == "gpu" and "episodes" in b.name
                and b.subject.streams[0].engine == "warp"]
    assert {(b.subject.streams[0].nbatch, len(b.subject.streams[0].terminate),
             b.subject.streams[0].continue_episodes) for b in episodes} == {
        (n, r, c) for n in (4096, 8192) for r in (1, 2) for c in (False, True)}
    with pytest.raises(ValueError, match="no workload named 'nope'"):
        W.select(["nope"], None)
    with pytest.raises(ValueError, match="suite: expected one of cpu, gpu, several-gpus, got 'tpu'"):
        W.select([], "tpu")


def run(benchmarks, tmp_path, **kw):
    out = tmp_path / "lines.jsonl"
    lines = suite.run(benchmarks, out, repeats=1, min_seconds=0.01, folder=str(tmp_path), **kw)
    assert results.read_lines([out]) == json.loads(json.dumps(lines))  # what was written
    return out, lines


def test_a_run_writes_lines_and_check_names_the_workload_below_target(tmp_path, capsys):
    easy = Benchmark("tiny-raw", "cpu", Method(W.SIMLOADER, (TINY,)), Method(W.RAW, (TINY,)),
                     1e-3, "a test")
    hard = Benchmark("tiny-impossible", "cpu",
                     Method(W.SIMLOADER, (TINY.but(record=("qpos", "xpos")),)),
                     Method(W.SIMLOADER, (TINY,)), 1e6, "a test")
    broken = Benchmark("tiny-broken", "cpu", Method(W.SIMLOADER, (TINY.but(terminate=(
        "below(nobody, 0.1)",)),)), Method(W.SIMLOADER, (TINY,)), 0.5, "a test")
    out, lines = run([easy, hard, broken], tmp_path)
    subjects = {line["workload"]: line for line in lines if line["role"] == "subject"}
    assert subjects["tiny-raw"]["passed"] and subjects["tiny-raw"]["ratio"] > 0
    assert subjects["tiny-impossible"]["passed"] is False
    # below its target, measured again with as many repetitions before the verdict; a
    # workload at its target is not
    assert subjects["tiny-impossible"]["repeated_below_target"] == 1
    assert subjects["tiny-impossible"]["repeats"] == 2
    assert subjects["tiny-raw"]["repeated_below_target"] == 0
    assert subjects["tiny-raw"]["repeats"] == 1
    assert "nobody" in subjects["tiny-broken"]["error"]
    for line in lines:
        if "error" not in line:
            assert line["units_per_s"] > 0 and math.isfinite(line["first_s"])
            # every repetition kept, the median of them the line's rate
            reps = line["repetitions_s"]
            assert len(reps) == line["repeats"] and all(r > 0 for r in reps)
            assert line["units_per_s"] == pytest.approx(1 / statistics.median(reps))
            assert line["machine"]["cpus"] >= 1 and line["versions"]["mujoco"]
            assert line["date"] and "commit" in line
    missed = results.failures(results.read_lines([out]))
    assert [m.split(":")[0] for m in missed] == ["tiny-impossible", "tiny-broken"]
    assert "target 1000000.000x" in missed[0]
    # the report: a table of the latest rows and a plot; --check exits 1 naming them
    md, png = results.report(results.read_lines([out]), tmp_path / "report", "tiny", "Tiny")
    text = md.read_text()
    assert "| tiny-raw " in text and "**no**" in text and "failed" in text
    assert png.stat().st_size > 1000
    with pytest.raises(SystemExit) as e:
        cli.main(["bench", "report", str(out), "--out", str(tmp_path / "r"), "--check"])
    assert e.value.code == 1
    assert "tiny-impossible" in capsys.readouterr().err


def test_a_rerun_replaces_a_workloads_row(tmp_path):
    easy = Benchmark("tiny-raw", "cpu", Method(W.SIMLOADER, (TINY,)), Method(W.RAW, (TINY,)),
                     1e6, "a test")
    out, _ = run([easy], tmp_path)
    lines = results.read_lines([out])
    again = [dict(line, passed=True, ratio=2.0) if line["role"] == "subject" else line
             for line in lines]
    (row,) = results.latest(lines + again)
    assert row["ratio"] == 2.0 and row["baseline"]["role"] == "baseline"
    assert results.failures(lines + again) == []


def test_write_render_on_read_and_mixture_sides_measure(tmp_path, monkeypatch):
    monkeypatch.setattr(suite, "READ_WORKERS", 0)  # spawned workers: the suite's own run
    cam = TINY.but(record=("state",), camera=(16, 16), camera_quality=False)
    # what the user keeps in the folder the run is pointed at, a link out of it included
    outside = tmp_path.parent / f"{tmp_path.name}-outside"
    outside.mkdir()
    (outside / "data.bin").write_bytes(b"user's")
    (tmp_path / "keep.txt").write_text("user's")
    (tmp_path / "link").symlink_to(outside, target_is_directory=True)
    out, lines = run([
        Benchmark("tiny-write", "cpu", Method(W.WRITE, (TINY,)), Method(W.SIMLOADER, (TINY,)),
                  1e-3, "a test"),
        Benchmark("tiny-bound", "cpu", Method(W.WRITE, (TINY,)),
                  Method(W.WRITE_BOUND, (TINY,)), 1e-3, "a test"),
        Benchmark("tiny-read", "cpu", Method(W.READ_RENDER, (cam,)),
                  Method(W.SIMLOADER, (cam,)), 1e-3, "a test", unit="frames"),
        Benchmark("tiny-mixture", "cpu", Method(W.MIXTURE, (TINY, TINY.but(model="humanoid"))),
                  Method(W.MEMBERS, (TINY, TINY.but(model="humanoid"))), 1e-3, "a test",
                  min_calls=4),
    ], tmp_path)
    errors = [line.get("error") for line in lines if "error" in line]
    assert not errors, errors
    bound = next(line for line in lines if line["workload"] == "tiny-bound"
                 and line["role"] == "baseline")
    assert bound["extra"]["store_bytes_per_step"] > 0
    assert bound["extra"]["disk_steps_per_s"] > 0
    # the run removed the stores it made, made nothing else where it was pointed, and
    # touched nothing of the user's there or behind the link
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.txt", "lines.jsonl", "link"]
    assert (tmp_path / "keep.txt").read_text() == "user's"
    assert (tmp_path / "link").is_symlink()
    assert sorted(p.name for p in outside.iterdir()) == ["data.bin"]
    assert (outside / "data.bin").read_bytes() == b"user's"


def test_cli_bench_list_and_bad_names(capsys):
    cli.main(["bench", "list", "--suite", "gpu"])
    out = capsys.readouterr().out
    assert "warp-open-loop [gpu] target 0.970x" in out and "cpu-open-loop" not in out
    with pytest.raises(SystemExit) as e:
        cli.main(["bench", "run", "nope"])
    assert e.value.code == 2
    assert "no workload named 'nope'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["bench", "report", "missing.jsonl"])
    assert "no such file" in capsys.readouterr().err


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_raw_warp_restarts_its_worlds_unless_continued():
    pytest.importorskip("mujoco_warp")
    from simloader.bench import raw
    model = simloader.load_model("cartpole")
    w = raw.Workload("cartpole", 16, 5)
    restarted, continued = (raw.RawWarp(model, w, 0, continued=c) for c in (False, True))
    dt = model.opt.timestep
    for _ in range(2):
        t_restarted = restarted()["state"][:, :, 0].cpu()
        t_continued = continued()["state"][:, :, 0].cpu()
    # time is the state's first column: one step after the initial state, or 3 batches on
    # (two eager steps at construction, one per batch)
    assert torch.allclose(t_restarted[:, 0], torch.full((16,), dt), atol=1e-6)
    assert bool((t_continued[:, 0] > 5 * dt).all())


def test_startup_seconds_pool_what_both_children_run_alike():
    # before `import torch` ended both children run the same text: its noise is pooled (the
    # median of all children), simloader's own seconds (after torch) stay each side's
    subject = suite.Side(lambda n: 0.0, 0.0, 0.0,
                         extra={"before_torch_s": [3.9, 3.8, 3.0], "after_torch_s": []})
    baseline = suite.Side(lambda n: 0.0, 0.0, 0.0,
                          extra={"before_torch_s": [3.1, 3.2, 3.3], "after_torch_s": []})
    seconds = suite.startup_seconds({"subject": 4.0, "baseline": 3.5}, subject, baseline)
    assert seconds == pytest.approx({"subject": 4.0 + 3.25, "baseline": 3.5 + 3.25})


def test_ranks_side_splits_one_stream_over_torchrun_processes():
    # the several-gpus suite's ranks side, here on the CPU (gloo): two processes, each its own
    # part of the seeded stream, timed together; a fresh job per call after the warm one
    side = suite._ranks(TINY, 2, seed=0, timeout=240)
    seconds = side.measure(2)
    slowest, fastest = side.extra["slowest_rank_steps_per_s"], side.extra["fastest_rank_steps_per_s"]
    assert len(slowest) == len(fastest) == 1  # the warm-up job's cleared
    # per GPU: both ranks' steps over the slowest rank's seconds, halved
    assert seconds == pytest.approx(1 / slowest[0]) and slowest[0] <= fastest[0]
    assert side.call_s > 0 and side.first_s > 0


def test_a_workload_needing_more_gpus_than_the_machine_has_is_skipped_not_failed(tmp_path):
    gpus = torch.cuda.device_count() + 1
    on_gpus = TINY.but(engine="warp")
    needs = Benchmark("tiny-needs-gpus", "cpu", Method(W.RANKS, (on_gpus,), gpus),
                      Method(W.RANKS, (on_gpus,), 1), 0.9, "a test")
    assert needs.gpus == gpus and Method(W.SIM_DEVICES, (on_gpus,), 3).gpus == 4
    assert Method(W.RANKS, (TINY,), 2).gpus == 0 and Method(W.SIMLOADER, (on_gpus,)).gpus == 0
    out, lines = run([needs], tmp_path)
    line, = lines
    assert line["passed"] is None and "needs" in line["skipped"]
    assert results.failures(lines) == []
    assert "skipped: needs" in results.table(lines)
    # a report of this run and a measured one of another machine keeps the measured row
    measured = {"workload": "tiny-needs-gpus", "role": "subject", "ratio": 0.99,
                "passed": True, "target": 0.9}
    assert results.latest([measured, line])[0]["ratio"] == 0.99
    assert "skipped" in results.latest([line])[0]


def test_bench_run_says_a_workload_it_skips_and_runs_on(tmp_path, capsys):
    # warp-2-ranks needs 2 GPUs: skipped here, the run goes on to the table
    if torch.cuda.device_count() >= 2:
        pytest.skip("this machine runs it")
    cli.main(["bench", "run", "warp-2-ranks", "--out", str(tmp_path / "lines.jsonl")])
    out = capsys.readouterr().out
    assert "warp-2-ranks: skipped: needs 2 GPUs" in out and "| warp-2-ranks" in out


def test_a_ranks_job_past_its_time_leaves_no_rank_running():
    # torchrun starts its ranks in sessions of their own: a timeout stops them through it
    import pathlib
    import time

    from simloader.bench import ranks

    def running():
        found = []
        for proc in pathlib.Path("/proc").iterdir():
            try:
                cmdline = (proc / "cmdline").read_bytes()
            except OSError:
                continue
            if b"simloader.bench.ranks" in cmdline:
                found.append(proc.name)
        return found

    with pytest.raises(RuntimeError, match="timed out after 5 s"):
        ranks.job(TINY, 2, 10 ** 6, seed=0, timeout=5)  # the ranks are stepping by then
    deadline = time.monotonic() + 10
    while running() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert running() == []


def test_a_ratio_just_below_its_target_does_not_read_as_the_target():
    assert results.ratio_text({"ratio": 0.9497, "target": 0.95}) == "0.9497"
    assert results.ratio_text({"ratio": 0.95, "target": 0.95}) == "0.950"
    assert results.ratio_text({"ratio": 0.863, "target": 0.9}) == "0.863"
    assert results.ratio_text({"ratio": 1.2, "target": None}) == "1.200"
    assert results.ratio_text({"ratio": 0.94996, "target": 0.95}) == "0.94996"
    assert results.ratio_text({"ratio": 9.9996, "target": 10}) == "9.9996"  # numbers, not text
    line = {"workload": "w", "ratio": 0.9497, "target": 0.95, "passed": False}
    assert results.failures([dict(line, role="subject")]) == [
        "w: 0.9497x its baseline, target 0.950x"]
