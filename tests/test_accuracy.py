"""`simloader check` / `simloader.accuracy.check`: an engine's physics against MuJoCo C's from
the same states and controls. The CPU engine is MuJoCo C (exactly 0); MJX's drift on MuJoCo
Menagerie's UR5e (tests/robots: positions 3e-3 apart, velocities about 1.5 rad/s after one
step, as issue 64 measured on an H200 with raw `mjx.step`) is reported, not hidden."""

import pathlib

import pytest

from simloader import accuracy, cli

UR5E = pathlib.Path(__file__).parent / "robots" / "universal_robots_ur5e" / "scene.xml"


def test_the_cpu_engine_is_mujoco_c_exactly(capsys):
    got = accuracy.check("cartpole", "cpu", nbatch=4, nstep=30)
    assert got.one_step == {"qpos": 0.0, "qvel": 0.0}
    assert got.over_batch == {"qpos": 0.0, "qvel": 0.0}
    cli.main(["check", str(UR5E), "--backend", "cpu", "--nbatch", "2", "--nstep", "5"])
    out = capsys.readouterr().out
    assert "backend='cpu' against MuJoCo C" in out and "qvel" in out


def test_mjx_drift_on_the_ur5e_is_reported():
    pytest.importorskip("mujoco.mjx")
    got = accuracy.check(str(UR5E), "mjx", nbatch=2, nstep=10)
    assert got.backend == "mjx"
    assert got.one_step["qvel"] > 0.1  # the arm's drift: far beyond float32 rounding
    assert 1e-5 < got.one_step["qpos"] < 0.1
    assert "one step" in str(got) and "over the batch" in str(got)
