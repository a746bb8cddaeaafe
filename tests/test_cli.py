"""The `simloader` command line: info, quickstart and bench run and print what they promise."""

import re

import pytest

from simloader import bench, cli


def test_info_names_columns(capsys):
    cli.main(["info", "cartpole", "--control-spec", "ctrl|xfrc_applied"])
    out = capsys.readouterr().out
    assert "xfrc_applied" in out and "pole" in out


def test_info_names_recorded_keys(capsys):
    cli.main(["info", "cartpole", "--record", "qpos,xpos,sensor:tip_pos"])
    out = capsys.readouterr().out
    assert "recorded keys (nbatch, nframes, ...) and their named parts:" in out
    assert "xpos (3, 3): rows of world, cart, pole" in out
    assert "qpos (2,): rows of slider, hinge" in out


def test_quickstart_streams_and_reports_throughput(capsys):
    cli.main(["quickstart", "--backend", "rollout", "--nbatch", "8", "--nstep", "5",
              "--batches", "3"])
    out = capsys.readouterr().out
    assert re.search(r"throughput: [\d,]+ steps/s", out), out
    assert "'state': (8, 5," in out


def test_bench_rollout_table_and_plot(capsys, tmp_path):
    plot = tmp_path / "bench.png"
    cli.main(["bench", "cartpole", "--backends", "rollout", "--nbatch", "16", "--nstep", "10",
              "--repeats", "1", "--min-seconds", "0", "--python-steps", "100",
              "--plot", str(plot)])
    out = capsys.readouterr().out
    rows = {line.split("|")[3].strip(): line for line in out.splitlines()
            if line.startswith("| cartpole")}
    assert set(rows) == {bench.PYTHON, bench.RAW_ROLLOUT, bench.SIMLOADER_ROLLOUT}
    # the simloader row carries a measured throughput ratio to the raw rollout
    ratio = float(rows[bench.SIMLOADER_ROLLOUT].split("|")[7])
    assert 0 < ratio < 10
    assert plot.stat().st_size > 1000


def test_bench_rejects_unknown_backend():
    with pytest.raises(SystemExit):
        cli.main(["bench", "--backends", "warp"])


def test_compare_mjx_next_to_raw_mjx():
    pytest.importorskip("mujoco.mjx")
    model = cli.simloader.load_model("cartpole")
    s_per_step, runs_on, notes = bench.compare(
        model, bench.Workload("cartpole", 8, 5), ["mjx"], repeats=1, min_batches=1,
        min_seconds=0, python_steps=50)
    assert set(s_per_step) == {bench.RAW_MJX, bench.SIMLOADER_MJX, bench.PYTHON}
    assert all(s > 0 for s in s_per_step.values())
    assert notes[0].startswith("mjx: impl=") and "compiled" in notes[1]
