"""Shared test models (small inline MJCF with every kind of user input a control_spec drives),
JAX's compilation cache, and fresh Python processes that import this checkout."""

import os
import pathlib
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import torch

import simloader

# A free ball that lands on a plane (contacts), a two-link arm with a motor and a position
# actuator, a mocap body welded to the hand by an equality that starts inactive, sensors.
RICH_XML = """
<mujoco model="rich">
  <option timestep="0.005"/>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 .1"/>
    <body name="target" mocap="true" pos="0.5 0.5 1.2">
      <geom type="sphere" size="0.05" contype="0" conaffinity="0"/>
    </body>
    <body name="ball" pos="0 0 0.3">
      <freejoint name="ball"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
    <body name="arm" pos="0 0.5 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      <body name="hand" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03"/>
      </body>
    </body>
  </worldbody>
  <equality>
    <weld name="grab" body1="target" body2="hand" active="false"/>
  </equality>
  <actuator>
    <motor name="shoulder" joint="shoulder" ctrllimited="true" ctrlrange="-2 2"/>
    <position name="elbow" joint="elbow" kp="5" ctrllimited="true" ctrlrange="-1 1"/>
  </actuator>
  <sensor>
    <jointpos name="shoulder" joint="shoulder"/>
    <framepos name="ball" objtype="body" objname="ball"/>
  </sensor>
  <keyframe>
    <key name="raised" qpos="0 0 1 1 0 0 0 0.5 -0.5"/>
  </keyframe>
</mujoco>
"""

# A pendulum whose site sits near the largest float of a precision (`pos`): its position, a
# derived field no engine's divergence check restarts, overflows to inf once the pole has
# turned far enough (float32 at 2.6e38: where cos + |sin| > 1.31, 0.43-1.14 rad; float64 at
# 1.5e308 likewise), while the physics, which no site touches, stays finite. FAR_SITE_X0:
# eight poles at rest from -1.2 to 1.2 rad (time, qpos, qvel).
FAR_SITE_XML = """
<mujoco>
  <worldbody>
    <body name="pole">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05" mass="1"/>
      <site name="far" pos="{pos} 0 {pos}"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" ctrlrange="-1 1"/></actuator>
</mujoco>
"""
FAR_SITE_X0 = np.stack([np.zeros(8), np.linspace(-1.2, 1.2, 8), np.zeros(8)], axis=1)


def assert_far_site_restarts(first: dict, second: dict, x0: np.ndarray) -> torch.Tensor:
    """Two consecutive continuing batches of the far-site pendulum from initial states `x0`:
    exactly the trajectories whose recorded `site_xpos` holds a non-finite value are flagged,
    start the second batch afresh from x0, and the others continue where the first ended.
    Returns the flags (on the CPU)."""
    flagged = ~torch.isfinite(first["site_xpos"]).flatten(1).all(1).cpu()
    assert flagged.any() and not flagged.all()
    assert torch.equal(first["diverged"].cpu(), flagged)
    start = second["initial_state"].cpu().double()
    np.testing.assert_allclose(start[flagged].numpy(), x0[flagged.numpy()], rtol=1e-6)
    assert torch.equal(start[~flagged], first["state"][:, -1].cpu().double()[~flagged])
    return flagged

REPO = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def rich_model():
    return mujoco.MjModel.from_xml_string(RICH_XML)


@pytest.fixture(scope="session")
def humanoid_path():
    """The built-in DeepMind Control Suite humanoid: a contact-rich model every clone has."""
    return simloader.builtin_path("humanoid")


@pytest.fixture(scope="session")
def cache_dir(tmp_path_factory):
    """JAX's persistent compilation cache for the whole session. JAX takes the directory set
    before its first cached compilation and ignores later changes, so there is one."""
    return str(tmp_path_factory.mktemp("jax-cache"))


def _checkout_env(extra=None):
    """The environment of a child Python that imports this checkout's simloader (not another
    installed copy), with `extra` variables."""
    path = os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    return {**os.environ, **(extra or {}), "PYTHONPATH": path}


@pytest.fixture(scope="session")
def checkout_env():
    """`checkout_env(extra=None) -> env` for subprocesses that must import this checkout."""
    return _checkout_env


def _fresh_python(script, runs, timeout=300):
    """Runs `script` once per `(args, env)` of `runs`, each in a fresh interpreter that imports
    this checkout's simloader (not another installed copy), all at once; returns their stdouts.
    A run that fails or outlives `timeout` seconds fails the test (and is killed)."""
    procs = [subprocess.Popen([sys.executable, "-c", script, *map(str, args)],
                              env=_checkout_env(env), text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE)
             for args, env in runs]
    outputs = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=timeout)
            assert proc.returncode == 0, f"the script failed ({proc.args[3:]}):\n{err}"
            outputs.append(out)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return outputs


@pytest.fixture(scope="session")
def fresh_python():
    """`fresh_python(script, [(args, env), ...], timeout=300) -> [stdout, ...]`: the script run
    in fresh interpreters at once, importing this checkout."""
    return _fresh_python


# The heaviest test files (seconds on the 2-core CI machine, most of it MJX compilation), run
# first: `--dist loadfile` hands files to the two workers in collection order, and a heavy file
# collected last keeps one worker busy long after the other has finished.
HEAVY_FIRST = ("test_docs.py", "test_startup.py", "test_examples.py", "test_record_kinematics.py",
               "test_mjx.py", "test_store_faults.py", "test_distributed.py",
               "test_store_pixels.py", "test_accuracy.py", "test_warp.py",
               "test_store_pipeline.py", "test_mjx_resume.py", "test_tutorial.py",
               "test_mjx_randomize.py", "test_observe_mjx.py", "test_render_cpu.py",
               "test_policy.py")


def pytest_addoption(parser):
    parser.addoption("--soak", action="store_true", default=False,
                     help="run the soaks (marker `soak`: long stability runs, minutes each; "
                          "SIMLOADER_SOAK_SECONDS sets their length)")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable within a file
    # the soaks (tests/test_soak.py) run only when asked for: they take minutes each
    if not config.getoption("--soak"):
        skip = pytest.mark.skip(reason="a soak: run with --soak")
        for item in items:
            if item.get_closest_marker("soak") is not None:
                item.add_marker(skip)


# simloader.write of a cart-pole stream (64 x 400 per batch: long enough to be caught mid-way)
_WRITER = """
import sys, simloader
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=64, nstep=400, nthread=1,
                          seed=int(sys.argv[3]), control=simloader.controls.Uniform(), prefetch=1)
simloader.write(ds, sys.argv[1], batches=int(sys.argv[2]), progress=False)
"""


@pytest.fixture
def started_writer():
    """start(path, batches, slot, seed=0): a process writing `batches` batches of the stream
    of `_WRITER` to `path`, returned once batch slot `slot` is committed (or it ended)."""
    import subprocess
    import sys
    import time

    from simloader.store import zarr_format as store_format

    def start(path, batches, slot, seed=0):
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(path), str(batches),
                                 str(seed)])
        marker = os.path.join(path, store_format.WRITTEN.shard_key(slot))
        deadline = time.monotonic() + 120
        while not os.path.exists(marker) and time.monotonic() < deadline and \
                proc.poll() is None:
            time.sleep(0.01)
        return proc
    return start


@pytest.fixture(scope="module")
def warp_on_cpu(cache_dir):
    """MuJoCo Warp on the CPU where no GPU is (on a GPU the variable changes nothing), for a
    module's tests (`pytestmark = pytest.mark.usefixtures("warp_on_cpu")`)."""
    before = os.environ.get("SIMLOADER_WARP_ON_CPU")
    os.environ["SIMLOADER_WARP_ON_CPU"] = "1"
    yield
    if before is None:
        del os.environ["SIMLOADER_WARP_ON_CPU"]
    else:
        os.environ["SIMLOADER_WARP_ON_CPU"] = before
