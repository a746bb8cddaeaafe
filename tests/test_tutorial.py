"""The tutorial page (docs/tutorial.md) runs as written: its ```python blocks in order, in one
namespace (each builds on the ones before), in a fresh folder beside the repository's
`examples/`, at the page's own sizes; and its command line works."""

import os
import pathlib
import subprocess
import sys

import pytest

from test_docs import python_blocks

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "tutorial.md"


def test_the_tutorial_runs_in_order(tmp_path, monkeypatch):
    pytest.importorskip("torchdata")
    pytest.importorskip("imageio_ffmpeg")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    blocks = python_blocks(PAGE)
    assert len(blocks) >= 6
    namespace = {"__name__": "__main__"}
    for block_id, code in blocks:
        exec(compile(code, block_id, "exec"), namespace)
    # what the page says it makes
    for made in ("walker.zarr", "walker.pt", "walker_open_loop.png", "walker.mp4"):
        assert (tmp_path / made).exists(), made
    # the resumed run went on from the checkpoint at batch 50 to batch 150
    import torch
    assert torch.load(tmp_path / "walker.pt")["step"] == 150
    assert namespace["loss"] < 1.0  # standardized: below the spread of the data


def test_the_tutorials_command_line():
    command = next(line for line in PAGE.read_text().splitlines()
                   if line.startswith("simloader info "))
    path = command.split()[-1]
    run = subprocess.run([sys.executable, "-m", "simloader.cli", "info", path], cwd=ROOT,
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert run.returncode == 0, run.stderr
    assert "rootz" in run.stdout and "left_ankle" in run.stdout
