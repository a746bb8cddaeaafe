"""Episodes that end (`terminate=`) on the Warp engine, inside its step graph: the flags the
rules imply, the fresh states of the initial-state source, MuJoCo's physics after a reset
within the named float32 tolerance, and episodes across batches resumed bit for bit. Without a
GPU these run MuJoCo Warp's CPU kernels (`SIMLOADER_WARP_ON_CPU=1`); on the GPU machine the
same tests run the captured CUDA graph. (The walker's kinematics and the resume across batches
are checked for every engine in test_terminate_mjx.py.)"""

import dataclasses

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


def after_step_verdict(kind):
    """Whether `episodes._after_step` finds one world's frame terminated by one rule of
    `kind` whose test every kind it knows would pass: qpos 0 within no interval, height 0
    below 2, tilt cosine 1 below 2."""
    import warp as wp

    from simloader.backends.warp import episodes
    one = dict(device="cpu")
    flags = [wp.zeros((1, 1), dtype=wp.bool, **one) for _ in range(3)]
    wp.launch(episodes._after_step, dim=1, inputs=[
        wp.zeros(1, dtype=wp.int64, **one), 1, 0, wp.array([kind], dtype=wp.int32, **one),
        wp.zeros(1, dtype=wp.int32, **one), wp.array([2.0], dtype=wp.float32, **one),
        wp.array([-2.0], dtype=wp.float32, **one), wp.zeros((1, 1), dtype=wp.vec3, **one),
        wp.array(np.eye(3, dtype=np.float32)[None, None], dtype=wp.mat33, **one),
        wp.zeros(1, dtype=wp.bool, **one), wp.zeros(1, dtype=wp.bool, **one),
        wp.zeros(1, dtype=wp.int64, **one), *flags, wp.zeros((1, 1), dtype=wp.float32, **one)],
        **one)
    return bool(flags[0].numpy()[0, 0])


def test_a_rule_kind_without_its_branch_meets_nothing_in_the_kernel():
    # each known kind has its branch; another falls into none (not into the tilt test)
    assert all(after_step_verdict(T.KINDS[k]) for k in ("outside", "below", "tilted"))
    assert not after_step_verdict(len(T.KINDS))


def test_a_free_bodys_height_rule_is_its_qpos_column_in_the_kernel():
    # Below on a body moved by a free joint alone is the row outside(z column, height, +inf):
    # the kernel's verdicts are the column's own, with no kinematics in the step
    import warp as wp

    from simloader.backends.warp import episodes
    rule = T.parse(simloader.load_model("humanoid"), T.Below("torso", 0.9)).rules[0]
    kind, column, low, high = rule.row()
    assert (kind, column, low, high) == (T.KINDS["outside"], rule.free_z, 0.9, float("inf"))
    z = np.array([2.0, 0.9, np.nextafter(np.float32(0.9), np.float32(0)), -1.0, np.inf],
                 dtype=np.float32)
    qpos = np.zeros((len(z), column + 1), dtype=np.float32)
    qpos[:, column] = z
    one = dict(device="cpu")
    n = len(z)
    flags = [wp.zeros((n, 1), dtype=wp.bool, **one) for _ in range(3)]
    wp.launch(episodes._after_step, dim=n, inputs=[
        wp.zeros(1, dtype=wp.int64, **one), 1, 0, wp.array([kind], dtype=wp.int32, **one),
        wp.array([column], dtype=wp.int32, **one), wp.array([low], dtype=wp.float32, **one),
        wp.array([high], dtype=wp.float32, **one), wp.zeros((n, 1), dtype=wp.vec3, **one),
        wp.zeros((n, 1), dtype=wp.mat33, **one), wp.zeros(n, dtype=wp.bool, **one),
        wp.zeros(n, dtype=wp.bool, **one), wp.zeros(n, dtype=wp.int64, **one), *flags,
        wp.array(qpos, dtype=wp.float32, **one)], **one)
    np.testing.assert_array_equal(flags[0].numpy()[:, 0], z < np.float32(0.9))
    np.testing.assert_array_equal(rule.met(np, {"qpos": qpos}), z < np.float32(0.9))


@dataclasses.dataclass(frozen=True)
class Above(T.Rule):
    """A rule of the user's own: the body's height above `height` (CPU and MJX evaluate its
    `met`; the Warp kernel has no branch for its kind)."""

    body: str
    height: float
    body_id: int = dataclasses.field(default=-1, repr=False)
    reads = ("xpos",)

    def resolve(self, model):
        return dataclasses.replace(self, body_id=mujoco.mj_name2id(
            model, mujoco.mjtObj.mjOBJ_BODY, self.body))

    def met(self, xp, fields):
        return fields["xpos"][:, self.body_id, 2] > self.height

    def row(self):
        return (len(T.KINDS), self.body_id, self.height, 0.0)


class Unrowed(Above):
    """A rule of the user's own without a row: `met` alone."""

    row = T.Rule.row


@pytest.mark.parametrize("rule, kind", [(Above("pole", 5.0), len(T.KINDS)),
                                        (Unrowed("pole", 5.0), None)])
def test_a_rule_kind_the_kernel_does_not_evaluate_is_refused_at_construction(rule, kind):
    with pytest.raises(ValueError, match=rf"terminate: {type(rule).__name__}\(body='pole', "
                                         rf"height=5.0\): its kind \(`row\(\)\[0\]`: {kind}\) "
                                         rf"is none the Warp engine's kernel evaluates: outside "
                                         rf"\(0\), below \(1\), tilted \(2\); use backend='cpu'"):
        simloader.SimDataset("cartpole", nbatch=2, nstep=2, backend="warp", terminate=rule)
    simloader.SimDataset("cartpole", nbatch=2, nstep=2, backend="cpu", terminate=rule)
