"""`simloader bench` times each engine next to a raw loop of that very engine: MJX-JAX next
to `RawMjx`, the Warp engine (the public mujoco_warp from torch) next to `RawWarp`, not next
to MJX's vendored Warp through JAX."""

import subprocess
import sys

import pytest
import torch

import simloader
from simloader import bench

pytest.importorskip("mujoco.mjx")


def resolved_backend(backend, monkeypatch):
    """The engine a real dataset of `backend` runs (Warp's on the CPU where no GPU is:
    resolving sizes the buffers, it simulates nothing)."""
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    ds = simloader.SimDataset("cartpole", backend=backend, nbatch=2, nstep=2,
                              control=simloader.controls.Uniform())
    return ds.config.backend


@pytest.mark.parametrize("backend, expected", [("mjx", "RawMjx"), ("warp", "RawWarp")])
def test_raw_baseline_runs_the_engine_simloader_runs(monkeypatch, backend, expected):
    if backend == "warp":
        pytest.importorskip("mujoco_warp")
    assert resolved_backend(backend, monkeypatch) == backend
    raw = bench.raw_baseline(backend)
    assert raw is getattr(bench, expected)
    # the table compares simloader's row of that engine with this baseline's row
    assert bench.RAW_OF[raw.simloader_row] == raw.row


def test_raw_baseline_rejects_unknown_backend():
    with pytest.raises(ValueError, match="backend: expected 'mjx' or 'warp', got 'cpu'"):
        bench.raw_baseline("cpu")


def test_bench_imports_without_warp():
    # the baselines import their engines when built: `simloader bench` on the rollout backend
    # runs where MuJoCo Warp is not installed
    code = ("import sys; sys.modules['warp'] = sys.modules['mujoco_warp'] = None; "
            "import simloader.bench; assert 'jax' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="RawWarp replays a CUDA graph")
def test_raw_warp_does_the_same_work_with_the_dataset_sizes(monkeypatch):
    pytest.importorskip("mujoco_warp")
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    options = simloader.SimDataset("cartpole", backend="warp", nbatch=2, nstep=2,
                                   control=simloader.controls.Uniform()).config.options
    model = simloader.load_model("cartpole")
    w = bench.Workload("cartpole", 2, 2)
    raw = bench.raw_baseline("warp").matching(model, w, 0, options)
    assert (raw.d.naconmax, raw.d.njmax) == (options.naconmax, options.njmax)
    nstate = 1 + model.nq + model.nv + model.na
    assert raw.shapes == {"state": (2, 2, nstate), "sensordata": (2, 2, model.nsensordata),
                          "control": (2, 2, model.nu)}
    out = raw()
    low, high = (torch.as_tensor(b, device=out["control"].device) for b in
                 bench.ctrl_bounds(model))
    assert torch.all((out["control"] >= low) & (out["control"] <= high))
    assert torch.all(torch.isfinite(out["state"])) and raw.measure(1) > 0
