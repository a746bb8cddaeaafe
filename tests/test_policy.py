"""Closed loop (`policy=`): the policy picks every step's controls from the observations before
the step. The CPU backend equals a plain loop of `mj_step` + the same policy bit for bit; MJX
(both implementations) follows it within float32 tolerances; noise, extras, the weights'
version, workers and the refusals."""

import copy
import json

import mujoco
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import simloader
from simloader import controls
from simloader import randomize as dr

S = mujoco.mjtState


class Feedback(torch.nn.Module):
    """A deterministic MLP of (qpos, qvel), float64, saturating past the control range at
    times (so MuJoCo's clamp is exercised)."""

    def __init__(self, nin, nout, seed=0):
        super().__init__()
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(nin, 16), torch.nn.Tanh(),
                                       torch.nn.Linear(16, nout)).double()

    def forward(self, obs):
        x = torch.cat([obs["qpos"], obs["qvel"]], -1).to(self.net[0].weight.dtype)
        u = 3 * self.net(x)
        return u, {"value": u.sum(-1), "seen": obs["qpos"]}


def plain_loop(models, x0, policy, nstep, noise=None):
    """MuJoCo C, one MjData per trajectory stepped in lockstep, the policy called on the batch
    of their observations before every step: qpos, qvel, xpos, sensordata and the applied
    controls after every step."""
    datas = [mujoco.MjData(m) for m in models]
    for m, d, x in zip(models, datas, x0):
        mujoco.mj_setState(m, d, x, S.mjSTATE_FULLPHYSICS)
        mujoco.mj_forward(m, d)
    out = {k: [] for k in ("qpos", "qvel", "xpos", "sensordata", "control")}
    for t in range(nstep):
        obs = {"qpos": torch.tensor(np.stack([d.qpos for d in datas])),
               "qvel": torch.tensor(np.stack([d.qvel for d in datas]))}
        with torch.no_grad():
            u = policy(obs)[0].numpy()
        if noise is not None:
            u = u + noise[:, t]
        for m, d, row in zip(models, datas, u):
            low, high = m.actuator_ctrlrange.T
            d.ctrl[:] = np.clip(row, low, high)
            mujoco.mj_step(m, d)
        for k in ("qpos", "qvel", "xpos", "sensordata"):
            out[k].append(np.stack([getattr(d, k).copy() for d in datas]))
        out["control"].append(np.stack([d.ctrl.copy() for d in datas]))
    return {k: np.stack(v, 1) for k, v in out.items()}


RECORD = ("qpos", "qvel", "xpos", "sensor:pole_angle", "sensordata")


def cartpole_policy():
    model = simloader.load_model("cartpole")
    return model, Feedback(model.nq + model.nv, model.nu)


@pytest.mark.parametrize("every", [1, 3])
def test_cpu_equals_a_plain_mj_step_loop_bit_for_bit(every):
    model, policy = cartpole_policy()
    ds = simloader.SimDataset(model, backend="rollout", nbatch=6, nstep=12, record=RECORD,
                              record_every=every, policy=policy, nthread=2,
                              initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    batch = next(iter(ds))
    ref = plain_loop([model] * 6, batch["initial_state"].numpy(), policy, 12)
    frames = slice(every - 1, None, every)
    for key in ("qpos", "qvel", "xpos", "sensordata"):
        assert np.array_equal(batch[key].numpy(), ref[key][:, frames]), key
    assert np.array_equal(batch["sensor:pole_angle"].numpy(), ref["sensordata"][:, frames, 1:2])
    assert np.array_equal(batch["control"].numpy(), ref["control"])
    # the controls were clamped somewhere (the policy saturates)
    assert np.abs(batch["control"].numpy()).max() == 1.0
    # extras every step; what the policy saw first is the initial state
    assert batch["policy/value"].shape == (6, 12)
    assert np.array_equal(batch["policy/seen"][:, 0].numpy(),
                          batch["initial_state"][:, 1:1 + model.nq].numpy())
    assert np.array_equal(batch["policy/seen"][:, 1:].numpy(), ref["qpos"][:, :-1])


def test_cpu_continuing_variants_randomized_and_noisy():
    """Two continuing batches of a randomized model with noise around the policy: the
    physics equals MuJoCo C given the delivered controls, and every delivered control is the
    policy's row plus the noise, clamped."""
    model, policy = cartpole_policy()
    spec = [dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole")]
    ds = simloader.SimDataset(model, backend="rollout", nbatch=5, nstep=8, record=RECORD,
                              policy=policy, policy_noise=controls.Normal(std=0.3),
                              continue_episodes=True, randomize=spec, nthread=2, seed=4)
    it = iter(ds)
    first, second = next(it), next(it)
    masses = first["params"]["body_mass[pole]"].numpy()
    models = []
    for i in range(5):
        m = simloader.load_model("cartpole")
        m.body_mass[m.body("pole").id] = masses[i, 0]  # the value it ran with
        mujoco.mj_setConst(m, mujoco.MjData(m))
        models.append(m)
    both = np.concatenate([first["control"].numpy(), second["control"].numpy()], 1)
    ref = plain_loop(models, first["initial_state"].numpy(),
                     lambda obs: (torch.zeros(5, 1, dtype=torch.float64),), 16, noise=both)
    assert np.array_equal(np.concatenate([first["qpos"], second["qpos"]], 1), ref["qpos"])
    for batch in (first, second):
        # controls: clamp(policy(obs) + noise), noise of the right spread
        obs_q = np.concatenate([batch["initial_state"][:, None, 1:3].numpy(),
                                batch["qpos"][:, :-1].numpy()], 1)
        obs_v = np.concatenate([batch["initial_state"][:, None, 3:5].numpy(),
                                batch["qvel"][:, :-1].numpy()], 1)
        with torch.no_grad():
            u = policy({"qpos": torch.tensor(obs_q), "qvel": torch.tensor(obs_v)})[0].numpy()
        noise = batch["control"].numpy() - u
        inside = np.abs(batch["control"].numpy()) < 1
        assert inside.sum() > 10 and 0.15 < noise[inside].std() < 0.5
    assert np.array_equal(second["initial_state"][:, 1:].numpy(),
                          np.concatenate([first["qpos"][:, -1], first["qvel"][:, -1]], 1))
    # the same seed and weights give the same stream
    again = next(iter(simloader.SimDataset(
        model, backend="rollout", nbatch=5, nstep=8, record=RECORD, policy=policy,
        policy_noise=controls.Normal(std=0.3), continue_episodes=True, randomize=spec,
        nthread=2, seed=4)))
    assert torch.equal(again["control"], first["control"])


@pytest.mark.parametrize("impl", ["jax", "warp"])
def test_mjx_follows_the_cpu_closed_loop(impl, cache_dir, monkeypatch):
    pytest.importorskip("mujoco.mjx")
    if impl == "warp":
        pytest.importorskip("warp")
        monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    model, policy = cartpole_policy()
    policy.float()
    kwargs = dict(nbatch=4, nstep=10, record=("qpos", "qvel"), policy=policy, seed=2,
                  dtype=torch.float32, initial_state=simloader.initial.Perturbed())
    cpu = next(iter(simloader.SimDataset(model, backend="rollout", **kwargs)))
    if torch.cuda.is_available():  # the policy lives where the simulation runs
        kwargs["policy"] = copy.deepcopy(policy).cuda()
    ds = simloader.SimDataset(model, backend="mjx", impl=impl, compilation_cache=cache_dir,
                              **kwargs)
    it = iter(DataLoader(ds, batch_size=None))
    gpu, gpu2 = next(it), next(it)
    assert torch.equal(gpu["initial_state"].cpu(), cpu["initial_state"])
    for key in ("qpos", "qvel", "control"):
        np.testing.assert_allclose(gpu[key].cpu().numpy(), cpu[key].numpy(), atol=2e-3,
                                   err_msg=key)
    assert gpu["policy/value"].shape == (4, 10)
    assert not gpu2["diverged"].any() and not torch.equal(gpu2["qpos"], gpu["qpos"])


def test_weights_version_follows_training():
    model, policy = cartpole_policy()
    opt = torch.optim.SGD(policy.parameters(), lr=1e-3)
    ds = simloader.SimDataset(model, backend="rollout", nbatch=2, nstep=3, policy=policy,
                              record=("qpos", "qvel"), nthread=1, prefetch=1)
    versions = [int(next(iter(ds))["policy/version"])]
    for _ in range(3):
        policy.zero_grad()
        sum(p.sum() for p in policy.parameters()).backward()
        opt.step()
    versions.append(int(next(iter(ds))["policy/version"]))
    assert versions[1] > versions[0]
    policy.version = 7  # the user's own counter wins
    assert int(next(iter(ds))["policy/version"]) == 7


def test_refusals():
    model, policy = cartpole_policy()
    base = dict(backend="rollout", nbatch=2, nstep=3, record=("qpos", "qvel"))
    with pytest.raises(ValueError, match="control, policy"):
        simloader.SimDataset(model, policy=policy, control=controls.Uniform(), **base)
    with pytest.raises(ValueError, match="policy_noise: .*needs policy="):
        simloader.SimDataset(model, policy_noise=controls.Normal(std=0.1), **base)
    with pytest.raises(TypeError, match="policy: expected a callable"):
        simloader.SimDataset(model, policy="pid", **base)
    with pytest.raises(ValueError, match=r"policy: control rows must have shape \(nbatch, "
                                         r"ncontrol\) = \(2, 1\).*got \(2, 3\)"):
        next(iter(simloader.SimDataset(model, policy=lambda obs: torch.zeros(2, 3), **base)))
    with pytest.raises(TypeError, match="policy: expected it to return control rows as a "
                                        "torch.Tensor"):
        next(iter(simloader.SimDataset(model, policy=lambda obs: np.zeros((2, 1)), **base)))


class Bias(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.bias = torch.nn.Parameter(torch.full((1,), 0.5, dtype=torch.float64))

    def forward(self, obs):
        return self.bias.expand(obs["qpos"].shape[0], 1)


# A forked worker holds a copy-on-write copy of the policy: refused unless its tensors were put
# in shared memory first. Run in a fresh process (fork after torch ran its thread pool may hang).
FORKED_WORKERS = """
import json, sys, torch
from torch.utils.data import DataLoader
import simloader


class Bias(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.bias = torch.nn.Parameter(torch.full((1,), 0.5, dtype=torch.float64))

    def forward(self, obs):
        return self.bias.expand(obs["qpos"].shape[0], 1)


policy = Bias()
if sys.argv[1] == "shared":
    policy.share_memory()
ds = simloader.SimDataset("cartpole", backend="rollout", nbatch=2, nstep=3, policy=policy,
                          record=("qpos",), nthread=1, num_batches=40, prefetch=1)
seen = []
try:
    for i, batch in enumerate(DataLoader(ds, batch_size=None, num_workers=2,
                                         multiprocessing_context="fork")):
        seen.append(float(batch["control"][0, 0, 0]))
        if i == 2:
            with torch.no_grad():
                policy.bias.fill_(-0.5)
except RuntimeError as e:
    seen = str(e)
print(json.dumps(seen))
"""


def test_forked_workers_need_shared_weights(fresh_python):
    refused, shared = (json.loads(out) for out in fresh_python(
        FORKED_WORKERS, [(["copied"], {}), (["shared"], {})], timeout=120))
    assert "share_memory" in refused
    # the training process's updates reach the workers
    assert shared[0] == 0.5 and shared[-1] == -0.5


def test_spawned_workers_share_the_weights():
    """Sending the policy to a spawned worker puts its CPU tensors in shared memory (torch's
    pickler), so updates reach the workers without share_memory()."""
    policy = Bias()
    ds = simloader.SimDataset("cartpole", backend="rollout", nbatch=2, nstep=3, policy=policy,
                              record=("qpos",), nthread=1, num_batches=40, prefetch=1)
    seen = []
    for i, batch in enumerate(DataLoader(ds, batch_size=None, num_workers=2,
                                         multiprocessing_context="spawn")):
        seen.append(float(batch["control"][0, 0, 0]))
        if i == 2:
            with torch.no_grad():
                policy.bias.fill_(-0.5)
    assert seen[0] == 0.5 and seen[-1] == -0.5


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("impl", ["jax", "warp"])
def test_mjx_closed_loop_never_waits_on_the_host(impl, cache_dir):
    """Dispatching a closed-loop batch makes no host synchronisation: torch's sync debug
    mode raises on any synchronising torch call, JAX's transfer guard on any device-to-host
    transfer. On Warp: MuJoCo Warp's own loop, its graph replayed on torch's stream."""
    import jax
    from simloader import sharding
    if impl == "warp":
        pytest.importorskip("warp")
    model, policy = cartpole_policy()
    policy.float().cuda()
    ds = simloader.SimDataset(model, backend="mjx", impl=impl, nbatch=64, nstep=20,
                              policy=policy, record=("qpos", "qvel"),
                              compilation_cache=cache_dir)
    next(iter(ds))  # compiles
    backend = ds.make_backend(sharding.current_shard(0))
    assert type(backend.program.closed_loop).__name__ == {"jax": "ClosedLoop",
                                                          "warp": "WarpLoop"}[impl]
    backend.produce(0)  # the first batch of an iterator sets its buffers up
    torch.cuda.set_sync_debug_mode("error")
    try:
        with jax.transfer_guard_device_to_host("disallow"):
            produced = backend.produce(1)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert backend.deliver(produced)["qpos"].shape == (64, 20, 2)


# -- MuJoCo Warp's own closed loop (`backends/mjx/warp_loop.py`) ----------------------------

class Pusher(torch.nn.Module):
    """A deterministic float32 policy for the rich model's six inputs (`EVERY_INPUT`): bounded
    controls and forces of (qpos, qvel), the grab switched on after 0.015 s, and a torque of
    1e9 on trajectory 1's ball from its fourth step on: a legal control (under mjMAXVAL) whose
    acceleration is not (it diverges, is flagged and restarted)."""

    def __init__(self, nq, nv, ncontrol, ctrl_columns):
        super().__init__()
        torch.manual_seed(3)
        self.lin = torch.nn.Linear(nq + nv, ncontrol)
        self.ctrl, self.nv = ctrl_columns, nv

    def forward(self, obs):
        u = 2 * torch.tanh(self.lin(torch.cat([obs["qpos"], obs["qvel"]], -1)))
        late = obs["time"] > 0.015
        u[:, -1] = late.to(u.dtype)  # eq_active: the last column
        fault = torch.zeros_like(u)
        fault[1, self.ctrl + 3] = 1e9 * late[1].to(u.dtype)  # qfrc_applied[3]: a ball dof
        return u + fault, {"late": late}


def _both_drivers(monkeypatch, cache_dir, model, nbatches, **kwargs):
    """The batches of MuJoCo Warp's own closed loop, and of the MJX closed loop (jitted
    single steps through MJX's Warp FFI) on the same configuration."""
    from simloader.backends.mjx import backend, warp_loop
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")  # on a GPU: the GPU, CUDA graphs
    if torch.cuda.is_available():
        kwargs["policy"] = kwargs["policy"].cuda()
    runs = {}
    for driver in ("warp", "mjx"):
        with monkeypatch.context() as patch:
            if driver == "mjx":
                patch.setattr(warp_loop, "WarpLoop", lambda pieces, closed, *args: closed)
            ds = simloader.SimDataset(model, backend="mjx", impl="warp", num_batches=nbatches,
                                      compilation_cache=cache_dir, **kwargs)
            # one at a time: the iterator ends (its thread joined) before the next starts
            runs[driver] = list(ds)
            (loop,) = [p.closed_loop for p in backend._PROGRAMS[ds.config].values()]
            assert type(loop).__name__ == {"warp": "WarpLoop", "mjx": "ClosedLoop"}[driver]
    return runs["warp"], runs["mjx"]


def _assert_same_batches(ours, theirs, atol):
    for a, b in zip(ours, theirs):
        assert sorted(a) == sorted(b)
        for key in a:
            if key == "params":
                for k in a[key]:
                    assert torch.equal(a[key][k], b[key][k]), k
            elif key == "policy/version" or not a[key].is_floating_point():
                assert torch.equal(a[key], b[key]), key
            else:
                np.testing.assert_allclose(a[key].cpu().numpy(), b[key].cpu().numpy(),
                                           atol=atol, rtol=0, err_msg=key)


def test_warp_loop_equals_the_mjx_driver_continuing_randomized_noisy(monkeypatch, cache_dir):
    """MuJoCo Warp's own loop computes what the MJX closed loop computes (the same MuJoCo
    Warp kernels, here on the CPU): reset, randomized damping, noise around the policy,
    MuJoCo's clamp, frames every 2nd step of a state, fields and sensors, continuation."""
    pytest.importorskip("warp")
    model, policy = cartpole_policy()
    policy.float()
    ours, theirs = _both_drivers(
        monkeypatch, cache_dir, model, 2, nbatch=4, nstep=8, record_every=2,
        record=("state", "qpos", "qvel", "xpos", "qacc", "sensor:pole_angle", "sensordata"),
        policy=policy, policy_noise=controls.Normal(std=0.3), continue_episodes=True,
        randomize=[dr.scale("dof_damping", dr.Uniform(50.0, 200.0))], seed=5,
        initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    _assert_same_batches(ours, theirs, atol=1e-5)
    first, second = ours
    assert first["qpos"].shape == (4, 4, 2) and first["policy/value"].shape == (4, 8)
    assert np.abs(first["control"].cpu().numpy()).max() == 1.0  # clamped where MuJoCo clamps
    assert torch.equal(second["initial_state"], first["state"][:, -1])  # continued


def test_warp_loop_equals_the_mjx_driver_on_contacts_every_input_and_a_fault(
        monkeypatch, cache_dir, rich_model):
    """Contacts (the ball on the floor), every control_spec input, and a trajectory driven
    to divergence: flagged, restarted, and the others as the MJX driver has them; every 4th
    step recorded."""
    pytest.importorskip("warp")
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED | S.mjSTATE_XFRC_APPLIED
               | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT | S.mjSTATE_EQ_ACTIVE)
    m = rich_model
    policy = Pusher(m.nq, m.nv, mujoco.mj_stateSize(m, spec), m.nu)
    ours, theirs = _both_drivers(
        monkeypatch, cache_dir, m, 1, nbatch=3, nstep=12, record_every=4, control_spec=spec,
        policy=policy,
        record=("time", "qpos", "qvel", "qfrc_constraint", "sensordata"), seed=1)
    _assert_same_batches(ours, theirs, atol=1e-4)
    (batch,) = ours
    assert batch["qpos"].shape == (3, 3, m.nq) and batch["control"].shape[1] == 12
    assert batch["diverged"].tolist() == [False, True, False]
    assert torch.isfinite(batch["qpos"]).all()  # restarted, never NaN
    assert (batch["qfrc_constraint"][0, :, :6].abs().sum() > 0).item()  # the ball is on the floor


def test_auto_takes_warps_own_loop_for_a_policy(monkeypatch, cache_dir):
    """impl="auto" runs a contact-free model on MJX-JAX open loop, but a policy in the loop
    on MuJoCo Warp's own driver (one graph replay per step instead of a jitted MJX call)."""
    pytest.importorskip("warp")
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    model, policy = cartpole_policy()
    kwargs = dict(backend="mjx", nbatch=2, nstep=2, compilation_cache=cache_dir)
    assert simloader.SimDataset(model, **kwargs).config.options.impl == "jax"
    ds = simloader.SimDataset(model, policy=policy, record=("qpos", "qvel"), **kwargs)
    assert ds.config.options.impl == "warp"
    assert "a policy in the loop runs fastest on MuJoCo Warp's own CUDA graph" in ds.describe()


def test_warp_loop_renders_what_the_mjx_driver_renders(monkeypatch, cache_dir):
    """A policy that sees a camera: MuJoCo Warp's own loop renders with MuJoCo Warp's renderer
    after the step, as the MJX driver renders inside its jitted steps (poses brought to the
    state, restarts included); the images and what the policy did with them agree."""
    pytest.importorskip("warp")

    class Looks(torch.nn.Module):
        """Pushes the cart by how much of the image is lit, and keeps what it saw."""

        def forward(self, obs):
            rgb = obs["camera/front/rgb"].float().mean(dim=(1, 2, 3))
            u = torch.tanh(rgb[:, None] / 64 - 1 + obs["qvel"][:, :1])
            return u, {"depth": obs["camera/front/depth"].mean(dim=(1, 2))}

    camera = simloader.Camera("front", height=16, width=24, depth=True, segmentation=True)
    ours, theirs = _both_drivers(
        monkeypatch, cache_dir, "cartpole", 1, nbatch=3, nstep=6, policy=Looks(),
        record=("qpos", "qvel", camera), seed=3, dtype=torch.float32,
        initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    (a,), (b,) = ours, theirs
    seg_a, seg_b = a["camera/front/segmentation"], b["camera/front/segmentation"]
    assert (seg_a == seg_b).float().mean() > 0.99 and (seg_a >= 0).any()
    same = seg_a == seg_b
    depth_a, depth_b = a["camera/front/depth"], b["camera/front/depth"]
    assert (depth_a[same] - depth_b[same]).abs().max() < 1e-3
    rgb_a, rgb_b = (x["camera/front/rgb"].int() for x in (a, b))
    assert a["camera/front/rgb"].dtype == torch.uint8 and rgb_a.float().mean() > 10
    assert (rgb_a - rgb_b).abs()[same].float().mean() < 1.0
    for key in ("qpos", "qvel", "control", "policy/depth"):
        np.testing.assert_allclose(a[key].cpu().numpy(), b[key].cpu().numpy(), atol=1e-3,
                                   err_msg=key)
