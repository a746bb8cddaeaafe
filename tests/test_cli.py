"""The `simloader` command line: info, quickstart and bench run and print what they promise."""

import re
import subprocess
import sys

import pytest

from simloader import cli
from simloader.tools import bench


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
    cli.main(["quickstart", "--backend", "cpu", "--nbatch", "8", "--nstep", "5",
              "--batches", "3"])
    out = capsys.readouterr().out
    assert re.search(r"throughput: [\d,]+ steps/s", out), out
    assert "'state': (8, 5," in out


def test_bench_rollout_table_and_plot(capsys, tmp_path):
    plot = tmp_path / "bench.png"
    cli.main(["bench", "cartpole", "--backends", "cpu", "--nbatch", "16", "--nstep", "10",
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
        cli.main(["bench", "--backends", "rollout"])  # the older spelling: not a bench row


def test_compare_mjx_next_to_raw_baseline_of_its_engine():
    pytest.importorskip("mujoco.mjx")
    model = cli.simloader.load_model("cartpole")
    s_per_step, runs_on, notes = bench.compare(
        model, bench.Workload("cartpole", 8, 5), ["mjx"], repeats=1, min_batches=1,
        min_seconds=0, python_steps=50)
    assert notes[0].startswith("mjx: raw: ") and "compiled" in notes[1]
    # the raw row is the engine simloader runs: MJX's jitted scan
    raw = bench.raw_baseline("mjx")
    assert raw is bench.RawMjx and f"raw: {raw.engine}" in notes[0]
    assert set(s_per_step) == {raw.row, raw.simloader_row, bench.PYTHON}
    assert all(s > 0 for s in s_per_step.values())


def _usage_error(capsys, argv):
    """Runs the command line, expecting a usage error: exit status 2 and one line on stderr."""
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    captured = capsys.readouterr()
    err = captured.err
    assert "Traceback" not in err and err.endswith("\n") and err.count("\n") == 1, err
    return err


@pytest.mark.parametrize("argv, expected", [
    (["info", "cartpol"], "model: expected an MJCF/MJB path"),
    (["quickstart", "--backend", "cpu", "--nbatch", "0"],
     "argument --nbatch: expected an integer >= 1, got '0'"),
    (["info", "cartpole", "--record", "qpso"], "record: unknown name 'qpso'"),
    (["warmup", "cartpol"], "got 'cartpol'"),
    (["bench", "cartpol"], "got 'cartpol'"),
    (["bench", "--nbatch", "0"], "argument --nbatch: expected an integer >= 1, got '0'"),
    (["quickstart", "--nbatch", "abc"], "argument --nbatch: expected an integer >= 1, got 'abc'"),
])
def test_bad_input_is_one_line_exit_2(capsys, argv, expected):
    err = _usage_error(capsys, argv)
    assert err.startswith(f"simloader {argv[0]}: error: ") and expected in err, err


def test_bad_input_from_entry_point_has_no_traceback(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "simloader.cli", "info", "cartpol"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1, proc.stderr
    assert "got 'cartpol' (no such file or model)" in proc.stderr and proc.stdout == ""


def test_simulation_errors_are_not_swallowed(monkeypatch):
    # only building from the arguments becomes a usage error; a failure while simulating
    # keeps its exception (and traceback)
    def fail(*args, **kwargs):
        raise ValueError("boom while simulating")
    monkeypatch.setattr(cli.simloader.SimDataset, "__iter__", fail)
    with pytest.raises(ValueError, match="boom while simulating"):
        cli.main(["quickstart", "--backend", "cpu", "--nbatch", "2", "--nstep", "2",
                  "--batches", "1"])


def test_quickstart_takes_model_positionally(capsys):
    cli.main(["quickstart", "humanoid", "--backend", "cpu", "--nbatch", "2", "--nstep", "2",
              "--batches", "1"])
    assert "model 'humanoid'" in capsys.readouterr().out


def test_quickstart_model_option_still_works(capsys):
    cli.main(["quickstart", "--model", "humanoid", "--backend", "cpu", "--nbatch", "2",
              "--nstep", "2", "--batches", "1"])
    assert "model 'humanoid'" in capsys.readouterr().out
    # the same model both ways is fine, two different ones are a usage error
    cli.main(["quickstart", "humanoid", "--model", "humanoid", "--backend", "cpu",
              "--nbatch", "2", "--nstep", "2", "--batches", "1"])
    assert "model 'humanoid'" in capsys.readouterr().out
    err = _usage_error(capsys, ["quickstart", "humanoid", "--model", "cartpole"])
    assert "'humanoid'" in err and "'cartpole'" in err


def test_every_subcommand_defaults_to_cartpole(capsys):
    cli.main(["info"])
    assert "pole" in capsys.readouterr().out
    cli.main(["quickstart", "--backend", "cpu", "--nbatch", "2", "--nstep", "2",
              "--batches", "1"])
    assert "model 'cartpole'" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out == f"simloader {cli.simloader.__version__}\n"


BENCH_FAST = ["--backends", "cpu", "--nbatch", "4", "--nstep", "5", "--repeats", "1",
              "--min-seconds", "0", "--python-steps", "20"]


def test_bench_writes_plot_into_out_folder(capsys, tmp_path):
    out = tmp_path / "results" / "nested"
    cli.main(["bench", *BENCH_FAST, "--out", str(out)])
    plot = out / "simloader-bench.png"
    assert plot.stat().st_size > 1000
    assert f"plot saved to {plot}" in capsys.readouterr().out


def test_bench_default_out_folder_not_cwd(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cli.main(["bench", *BENCH_FAST])
    assert not (tmp_path / "simloader-bench.png").exists()
    plot = tmp_path / cli.DEFAULT_OUT / "simloader-bench.png"
    assert plot.stat().st_size > 1000
    assert "plot saved to simloader-results" in capsys.readouterr().out


def test_bench_unusable_out_folder_is_usage_error(capsys, tmp_path):
    (tmp_path / "file").write_text("")
    err = _usage_error(capsys, ["bench", *BENCH_FAST, "--out", str(tmp_path / "file" / "x")])
    assert "--out" in err
