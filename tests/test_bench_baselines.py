"""`simloader bench` times each engine next to a raw loop of that very engine: MJX-JAX next
to `RawMjx`, the Warp engine (the public mujoco_warp from torch) next to `RawWarp`, not next
to MJX's vendored Warp through JAX."""

import subprocess
import sys
import types

import pytest
import torch

import simloader
from simloader import bench

pytest.importorskip("mujoco.mjx")


def resolved_options(impl, monkeypatch):
    """The options a real `backend="mjx"` dataset resolves for `impl` (Warp's on the CPU
    where no GPU is: resolving sizes the buffers, it simulates nothing)."""
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    ds = simloader.SimDataset("cartpole", backend="mjx", impl=impl, nbatch=2, nstep=2,
                              control=simloader.controls.Uniform())
    return ds.config.options


@pytest.mark.parametrize("impl, expected", [("jax", "RawMjx"), ("warp", "RawWarp")])
def test_raw_baseline_runs_the_engine_simloader_runs(monkeypatch, impl, expected):
    if impl == "warp":
        pytest.importorskip("mujoco_warp")
    options = resolved_options(impl, monkeypatch)
    assert options.impl == impl
    raw = bench.raw_baseline(options)
    assert raw is getattr(bench, expected)
    # the table compares simloader's row of that engine with this baseline's row
    assert bench.RAW_OF[raw.simloader_row] == raw.row


def test_raw_baseline_rejects_unknown_impl():
    with pytest.raises(ValueError, match="options.impl: expected 'jax' or 'warp', got 'cpu'"):
        bench.raw_baseline(types.SimpleNamespace(impl="cpu"))


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
    options = resolved_options("warp", monkeypatch)
    model = simloader.load_model("cartpole")
    w = bench.Workload("cartpole", 2, 2)
    raw = bench.raw_baseline(options).matching(model, w, 0, options)
    assert (raw.d.naconmax, raw.d.njmax) == (options.naconmax, options.njmax)
    nstate = 1 + model.nq + model.nv + model.na
    assert raw.shapes == {"state": (2, 2, nstate), "sensordata": (2, 2, model.nsensordata),
                          "control": (2, 2, model.nu)}
    out = raw()
    low, high = (torch.as_tensor(b, device=out["control"].device) for b in
                 bench.ctrl_bounds(model))
    assert torch.all((out["control"] >= low) & (out["control"] <= high))
    assert torch.all(torch.isfinite(out["state"])) and raw.measure(1) > 0
