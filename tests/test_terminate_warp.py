"""Episodes that end (`terminate=`) on the Warp engine, inside its step graph: the flags the
rules imply, the fresh states of the initial-state source, MuJoCo's physics after a reset
within the named float32 tolerance, and episodes across batches resumed bit for bit. Without a
GPU these run MuJoCo Warp's CPU kernels (`SIMLOADER_WARP_ON_CPU=1`); on the GPU machine the
same tests run the captured CUDA graph. (The walker's kinematics and the resume across batches
are checked for every engine in test_terminate_mjx.py.)"""

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

pytest.importorskip("warp")
pytest.importorskip("mujoco_warp")

import simloader  # noqa: E402
from simloader import controls, initial, seeds, sharding  # noqa: E402
from simloader import terminate as T  # noqa: E402
from test_terminate_mjx import CONTACT_FREE_TOL, resets  # noqa: E402

# MuJoCo Warp on the CPU where no GPU is (conftest.warp_on_cpu)
pytestmark = pytest.mark.usefixtures("warp_on_cpu")


def host(batch):
    return {k: v.cpu() for k, v in batch.items() if isinstance(v, torch.Tensor)}


@pytest.mark.parametrize("record_every", [1, 2])
def test_cartpole_flags_fresh_states_and_physics(record_every):
    ds = simloader.SimDataset("cartpole", nbatch=8, nstep=120, seed=5, backend="warp",
                              record_every=record_every, control=controls.Uniform(),
                              initial_state=initial.Perturbed(qpos_std=0.05, qvel_std=0.3),
                              terminate=[T.Outside("hinge", -0.3, 0.3), T.TimeLimit(40)])
    batch = host(next(iter(ds)))
    terminated, truncated, first = (batch[k].numpy() for k in ("terminated", "truncated",
                                                                "first"))
    hinge = batch["state"][..., 2].numpy()  # qpos of the hinge: [time, slider, hinge, ...]
    np.testing.assert_array_equal(terminated, (hinge < -0.3) | (hinge > 0.3))
    np.testing.assert_array_equal(first[:, 1:], (terminated | truncated)[:, :-1])
    assert first.sum() >= 8 and truncated.any()
    # the k-th reset of a row takes its draw k of the batch, as on the CPU engine
    draws = [ds.config.initial.sample(seeds.reset_seed(5, sharding.Shard(), 0, e), 8)
             for e in range(T.FRESH_DRAWS)]
    state, control = batch["state"].numpy(), batch["control"].numpy()
    model, data = ds.config.model, mujoco.MjData(ds.config.model)
    nframes = 120 // record_every
    checked = 0
    for row, frame, e in resets(first):
        np.testing.assert_array_equal(state[row, frame],
                                      draws[e % T.FRESH_DRAWS][row].astype(np.float32))
        steps = slice(frame * record_every, (frame + 1) * record_every)
        assert np.isnan(control[row, steps]).all()
        stop = next((j for j in range(frame + 1, nframes) if first[row, j]), nframes)
        if stop - frame < 2:
            continue
        u = control[row, (frame + 1) * record_every:stop * record_every].astype(np.float64)
        want, _ = rollout.rollout(model, data, state[row, frame].astype(np.float64)[None],
                                  u[None])
        np.testing.assert_allclose(state[row, frame + 1:stop],
                                   want[0, record_every - 1::record_every], rtol=0,
                                   atol=CONTACT_FREE_TOL)
        checked += 1
    assert checked >= 4
    assert np.isfinite(np.delete(control, np.flatnonzero(first.repeat(record_every, 1)
                                                         .ravel()), axis=None)).all()


def test_a_policy_sees_the_fresh_states():
    from test_terminate import check_closed_loop
    check_closed_loop("warp")


def test_a_callable_ends_episodes_as_a_rule_does():
    from test_terminate import check_callable
    check_callable("warp")
