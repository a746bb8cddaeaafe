"""The `simloader` command line: info, quickstart and bench run and print what they promise."""

import re
import subprocess
import sys

import pytest
import torch

from simloader import cli
from simloader import bench


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
              "--repeats", "1", "--min-seconds", "0.3", "--python-steps", "100",
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


def test_write_with_control_and_randomize_specs(capsys, tmp_path):
    out = tmp_path / "store"
    cli.main(["write", "--out", str(out), "--backend", "cpu", "--nbatch", "4", "--nstep", "6",
              "--batches", "2", "--seed", "7", "--control", "OU(std=0.3, tau=0.05)",
              "--randomize", "body_mass:pole=scale:uniform(0.8, 1.2)",
              "--randomize", "dof_damping:hinge=add:normal(0, 0.01, low=0, high=0.02)"])
    capsys.readouterr()
    stored = cli.simloader.StoredDataset(str(out))
    # the same dataset built in Python: the stored stream is its stream, bit for bit
    from simloader import controls
    from simloader import randomize as dr
    ds = cli.simloader.SimDataset(
        "cartpole", backend="cpu", nbatch=4, nstep=6, seed=7, num_batches=2, nthread=1,
        control=controls.OrnsteinUhlenbeck(std=0.3, tau=0.05),
        initial_state=cli.simloader.initial.Perturbed(),
        randomize=[dr.scale("body_mass", dr.Uniform(0.8, 1.2), on="pole"),
                   dr.add("dof_damping", dr.Normal(0.0, 0.01, low=0.0, high=0.02),
                          on="hinge")])
    batches = list(ds)
    assert len(stored) == 8
    for i in range(8):
        batch, row = batches[i // 4], i % 4
        assert torch.equal(stored[i]["control"], batch["control"][row])
        for key in ("body_mass[pole]", "dof_damping[hinge]"):
            assert torch.equal(stored[i]["params"][key], batch["params"][key][row])
    masses = torch.stack([stored[i]["params"]["body_mass[pole]"] for i in range(8)])
    damping = torch.stack([stored[i]["params"]["dof_damping[hinge]"] for i in range(8)])
    assert ((masses >= 0.08) & (masses < 0.12)).all() and masses.unique().numel() == 8
    base = float(cli.simloader.load_model("cartpole").joint("hinge").damping[0])
    assert ((damping >= base) & (damping <= base + 0.02 + 1e-15)).all()
    assert (damping == base).any()  # the normal's draws below 0 are clipped to low=0


def test_write_defaults_to_uniform_controls_without_randomization(capsys, tmp_path):
    help_text = subprocess.run([sys.executable, "-m", "simloader.cli", "write", "-h"],
                               capture_output=True, text=True, timeout=120).stdout
    flat = " ".join(help_text.split())
    assert "default: uniform, each actuator uniform in its ctrlrange" in flat
    assert "(default: no randomization)" in flat
    for name in ("uniform", "normal", "ornsteinuhlenbeck", "piecewiseconstant", "sinusoid",
                 "constant", "ou"):
        assert name in flat
    cli.main(["write", "--out", str(tmp_path / "s"), "--backend", "cpu", "--nbatch", "3",
              "--nstep", "4", "--batches", "1"])
    capsys.readouterr()
    stored = cli.simloader.StoredDataset(str(tmp_path / "s"))
    control = torch.stack([stored[i]["control"] for i in range(3)])
    assert "params" not in stored[0]
    assert control.abs().max() <= 1 and control.unique().numel() == control.numel()


@pytest.mark.parametrize("option, value, expected", [
    ("--control", "brownian", "argument --control: unknown name 'brownian' in 'brownian'; "
     "choices: uniform, normal, ornsteinuhlenbeck, piecewiseconstant, sinusoid, constant, ou"),
    ("--control", "ou(sigma=0.3)", "argument --control: ou has no argument 'sigma' (in "
     "'ou(sigma=0.3)'); its arguments: mean, std, tau, clip, on"),
    ("--control", "uniform(-1, 1)", "argument --control: uniform takes keyword arguments only "
     "(KEY=VALUE), got 'uniform(-1, 1)'; its arguments: low, high, on"),
    ("--control", "normal(std=__import__('os'))", "argument --control: normal.std: expected "
     "a number, a string or a tuple of them, got \"__import__('os')\""),
    ("--randomize", "body_mass", "argument --randomize: expected FIELD[:OBJ,...]=OP:DIST(ARGS), "
     "e.g. 'body_mass:pole=scale:uniform(0.8,1.2)', got 'body_mass'"),
    ("--randomize", "body_mass=times:uniform(1, 2)", "argument --randomize: unknown operation "
     "'times' in 'body_mass=times:uniform(1, 2)'; choices: set, scale, add"),
    ("--randomize", "body_mass=scale:gamma(1, 2)", "argument --randomize: unknown name 'gamma' "
     "in 'gamma(1, 2)'; choices: uniform, loguniform, normal"),
    ("--randomize", "body_mas:pole=scale:uniform(0.8, 1.2)", "randomize: 'body_mas' is not a "
     "floating-point MjModel field"),
])
def test_write_bad_spec_is_one_line_naming_the_option(capsys, tmp_path, option, value,
                                                      expected):
    err = _usage_error(capsys, ["write", "--out", str(tmp_path / "s"), "--backend", "cpu",
                                "--nbatch", "2", "--nstep", "2", "--batches", "1",
                                option, value])
    assert err.startswith("simloader write: error: ") and expected in err, err
    assert not (tmp_path / "s").exists()


# -- what #61 found: help, untrue output, progress into pipes, Ctrl-C, episodes ------------

def test_help_names_every_subcommand_and_every_options_default(capsys):
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    for name in ("quickstart", "write", "info", "bench", "warmup", "video"):
        assert f"`{name}`" in out, name  # the description says what each does
    with pytest.raises(SystemExit):
        cli.main(["write", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for said in ("--nbatch NBATCH trajectories per batch (default: 1024)",
                 "--nstep NSTEP steps per trajectory (default: 200)",
                 "--batches BATCHES batches in all (default: 20)",
                 "--num-workers NUM_WORKERS DataLoader workers that simulate and write in "
                 "parallel (default: 0)"):
        assert said in out, said


def test_write_says_what_it_wrote_and_nothing_when_the_store_was_complete(capsys, tmp_path):
    out = str(tmp_path / "s.zarr")
    argv = ["write", "--out", out, "--backend", "cpu", "--nbatch", "4", "--nstep", "5"]
    cli.main(argv + ["--batches", "2"])
    said = capsys.readouterr().out
    assert "wrote 2 x 4 trajectories of 5 steps" in said
    kept = re.search(r"kept: [\d.,]+ MB on disk for 40 steps, ([\d,]+) bytes per step", said)
    assert kept, said
    import os
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
    assert int(kept.group(1).replace(",", "")) == round(size / 40)
    cli.main(argv + ["--batches", "3"])
    said = capsys.readouterr().out
    assert "wrote 1 of the 3 x 4 trajectories" in said and "held the other 2" in said, said
    cli.main(argv + ["--batches", "3"])
    said = capsys.readouterr().out
    assert "nothing to write:" in said and "already holds the 3 x 4" in said, said
    assert "wrote" not in said.split("write:")[0]


def test_write_asks_for_episodes_with_terminate(capsys, tmp_path):
    import simloader
    out = str(tmp_path / "e.zarr")
    cli.main(["write", "--out", out, "--backend", "cpu", "--nbatch", "4", "--nstep", "60",
              "--batches", "1", "--terminate", "outside(hinge, -0.05, 0.05)",
              "--terminate", "timelimit(40)"])
    stored = simloader.StoredDataset(out)
    item = stored[0]
    assert {"terminated", "truncated", "first"} <= set(item)
    assert bool(item["first"].any())
    err = _usage_error(capsys, ["write", "--out", str(tmp_path / "f.zarr"), "--terminate",
                                "above(torso, 1)"])
    assert "--terminate: unknown name 'above'" in err and "below, tilted" in err


def test_write_records_the_frames_own_kinematics_when_asked(tmp_path):
    import mujoco
    import numpy as np
    import simloader
    out = str(tmp_path / "k.zarr")
    cli.main(["write", "--out", out, "--backend", "cpu", "--nbatch", "2", "--nstep", "5",
              "--batches", "1", "--record", "state,xpos", "--record-kinematics", "frame",
              "--quiet"])
    item = simloader.StoredDataset(out)[1]
    model = simloader.SimDataset("cartpole", backend="cpu", nbatch=1, nstep=1).model
    data = mujoco.MjData(model)
    for t in range(5):
        mujoco.mj_setState(model, data, item["state"][t].numpy(),
                           mujoco.mjtState.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(model, data)
        np.testing.assert_array_equal(item["xpos"][t].numpy(), data.xpos)


def test_warmup_of_the_cpu_engine_says_there_is_nothing_to_warm(capsys):
    cli.main(["warmup", "--nbatch", "4", "--nstep", "2"])
    out = capsys.readouterr().out
    assert "nothing to warm: the cpu engine compiles nothing" in out, out


def test_video_of_a_store_needs_no_model_and_takes_out_as_write_does(capsys, tmp_path):
    store = str(tmp_path / "v.zarr")
    cli.main(["write", "--out", store, "--backend", "cpu", "--nbatch", "2", "--nstep", "6",
              "--batches", "1"])
    capsys.readouterr()
    cli.main(["video", store, "--out", str(tmp_path / "a.gif"), "--rows", "0", "--size",
              "16", "16"])
    assert (tmp_path / "a.gif").stat().st_size > 0
    err = _usage_error(capsys, ["video", store, str(tmp_path / "b.gif"), "--out",
                                str(tmp_path / "c.gif")])
    assert "out: given twice and differently" in err


def test_no_progress_bar_into_a_pipe(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "simloader.cli", "write", "--out",
                           str(tmp_path / "p.zarr"), "--backend", "cpu", "--nbatch", "4",
                           "--nstep", "5", "--batches", "2"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "%|" not in proc.stderr and "it/s" not in proc.stderr, proc.stderr


def test_ctrl_c_is_one_line_exit_130_and_the_store_stays_readable(tmp_path):
    import os
    import signal
    import time
    import simloader
    out = str(tmp_path / "i.zarr")
    proc = subprocess.Popen([sys.executable, "-m", "simloader.cli", "write", "--out", out,
                             "--backend", "cpu", "--nbatch", "64", "--nstep", "200",
                             "--batches", "400"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    marks = os.path.join(out, "provenance", "written", "c")
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None and not (
            os.path.isdir(marks) and os.listdir(marks)):
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().count("\n") == 0, err
    assert err.startswith("simloader write: interrupted; the store at") and "resumes" in err
    assert len(simloader.StoredDataset(out)) >= 64  # what was committed is there, readable


def test_the_reference_page_is_made_from_the_parser_and_current():
    import pathlib
    page = pathlib.Path(__file__).parents[1] / "docs" / "cli.md"
    assert page.read_text() == cli.reference(), (
        "docs/cli.md is stale: python -m simloader.cli --reference > docs/cli.md")
