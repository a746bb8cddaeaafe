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
    ds = simloader.SimDataset(model, backend="cpu", nbatch=6, nstep=12, record=RECORD,
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
    ds = simloader.SimDataset(model, backend="cpu", nbatch=5, nstep=8, record=RECORD,
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
        model, backend="cpu", nbatch=5, nstep=8, record=RECORD, policy=policy,
        policy_noise=controls.Normal(std=0.3), continue_episodes=True, randomize=spec,
        nthread=2, seed=4)))
    assert torch.equal(again["control"], first["control"])


@pytest.mark.parametrize("impl", ["mjx", "warp"])
def test_mjx_follows_the_cpu_closed_loop(impl, cache_dir, monkeypatch):
    pytest.importorskip("mujoco.mjx")
    if impl == "warp":
        pytest.importorskip("warp")
        monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    model, policy = cartpole_policy()
    policy.float()
    every = 2  # frames after every other step: which of them a step writes, and when
    kwargs = dict(nbatch=4, nstep=10, record=("qpos", "qvel"), policy=policy, seed=2,
                  dtype=torch.float32, initial_state=simloader.initial.Perturbed(),
                  record_every=every)
    cpu = next(iter(simloader.SimDataset(model, backend="cpu", **kwargs)))
    if torch.cuda.is_available():  # the policy lives where the simulation runs
        kwargs["policy"] = copy.deepcopy(policy).cuda()
    if impl == "mjx":
        kwargs["compilation_cache"] = cache_dir
    ds = simloader.SimDataset(model, backend=impl, **kwargs)
    it = iter(DataLoader(ds, batch_size=None))
    gpu, gpu2 = next(it), next(it)
    assert torch.equal(gpu["initial_state"].cpu(), cpu["initial_state"])
    for key in ("qpos", "qvel", "control"):
        np.testing.assert_allclose(gpu[key].cpu().numpy(), cpu[key].numpy(), atol=2e-3,
                                   err_msg=key)
    assert gpu["policy/value"].shape == (4, 10)
    assert not gpu2["diverged"].any() and not torch.equal(gpu2["qpos"], gpu["qpos"])
    for out in (cpu, gpu):  # what the policy saw (its extra "seen" is obs["qpos"])
        seen = out["policy/seen"].cpu()
        assert seen.dtype == torch.float32  # `dtype=` applies to the observations too
        # step t's rows come from the state after t steps: the initial state, then the
        # state frame j records (after (j + 1) * every steps)
        torch.testing.assert_close(seen[:, 0], out["initial_state"].cpu()[:, 1:1 + model.nq])
        torch.testing.assert_close(seen[:, every::every], out["qpos"].cpu()[:, :-1])


def test_weights_version_follows_training():
    model, policy = cartpole_policy()
    opt = torch.optim.SGD(policy.parameters(), lr=1e-3)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=3, policy=policy,
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
    base = dict(backend="cpu", nbatch=2, nstep=3, record=("qpos", "qvel"))
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


class LaterRows:
    """Rows and extras as they should be at every step but `bad`, where `how` breaks them."""

    def __init__(self, how, bad=2):
        self.how, self.bad, self.t = how, bad, 0

    def __call__(self, obs):
        n = obs["qpos"].shape[0]
        u, extras = torch.zeros(n, 1, dtype=torch.float64), {"effort": torch.zeros(n)}
        if self.t == self.bad:
            if self.how == "one row":
                u = u[:1]
            elif self.how == "flat":
                u = u[:, 0]
            elif self.how == "integer":
                u = u.long()
            elif self.how == "new key":
                extras["surprise"] = torch.zeros(n)
            elif self.how == "missing key":
                extras = {}
            elif self.how == "extras shape":
                extras["effort"] = torch.zeros(n, 2)
            elif self.how == "extras dtype":
                extras["effort"] = torch.zeros(n, dtype=torch.float64)
        self.t += 1
        return u, extras


@pytest.mark.parametrize("how, error, message", [
    ("one row", ValueError, r"control rows must have shape .* = \(2, 1\).* at step 2, got "
                            r"\(1, 1\)"),
    ("flat", ValueError, r"at step 2, got \(2,\)"),
    ("integer", TypeError, r"control rows must be floating point at step 2, got torch.int64"),
    ("new key", ValueError, r"extras at step 2 have keys \['effort', 'surprise'\], at step 0 "
                            r"\['effort'\]"),
    ("missing key", ValueError, r"extras at step 2 have keys \[\], at step 0 \['effort'\]"),
    ("extras shape", ValueError, r"extras\['effort'\] at step 2 is torch.float32 \(2, 2\), "
                                 r"at step 0 torch.float32 \(2,\)"),
    ("extras dtype", ValueError, r"extras\['effort'\] at step 2 is torch.float64"),
])
def test_every_step_of_the_policy_is_checked(how, error, message):
    """A later step's rows would broadcast ((1, ncontrol), (ncontrol,)), be cast (integers),
    or break the extras' buffers made at step 0: each is refused, naming the step."""
    model, _ = cartpole_policy()
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=4, record=("qpos",),
                              policy=LaterRows(how))
    with pytest.raises(error, match="policy: " + ".*" + message):
        next(iter(ds))


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
if sys.argv[1] != "copied":
    if sys.argv[1] == "counted":  # a shared version counter the workers read
        policy.register_buffer("version", torch.zeros((), dtype=torch.int64))
    policy.share_memory()
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3, policy=policy,
                          record=("qpos",), nthread=1, num_batches=40, prefetch=1)
seen = []
try:
    for i, batch in enumerate(DataLoader(ds, batch_size=None, num_workers=2,
                                         multiprocessing_context="fork")):
        seen.append([float(batch["control"][0, 0, 0]), int(batch["policy/version"])])
        if i == 2:
            with torch.no_grad(), simloader.policy.updating(policy):
                policy.bias.fill_(-0.5)
except RuntimeError as e:
    seen = str(e)
print(json.dumps(seen))
"""


def test_forked_workers_need_shared_weights_and_a_shared_version(fresh_python):
    refused, uncounted, counted = (json.loads(out) for out in fresh_python(
        FORKED_WORKERS, [(["copied"], {}), (["shared"], {}), (["counted"], {})], timeout=120))
    assert "share_memory" in refused
    # shared weights whose version the workers cannot see are refused with what to write
    assert "register_buffer('version'" in uncounted
    # the training process's updates reach the workers, named by the version that made them
    assert counted[0] == [0.5, 0] and counted[-1] == [-0.5, 1]
    assert all(version == (value < 0) for value, version in counted)


def test_spawned_workers_share_the_weights():
    """Sending the policy to a spawned worker puts its CPU tensors in shared memory (torch's
    pickler), so updates reach the workers without share_memory()."""
    policy = Bias()
    policy.register_buffer("version", torch.zeros((), dtype=torch.int64))
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3, policy=policy,
                              record=("qpos",), nthread=1, num_batches=40, prefetch=1)
    seen = []
    for i, batch in enumerate(DataLoader(ds, batch_size=None, num_workers=2,
                                         multiprocessing_context="spawn")):
        seen.append((float(batch["control"][0, 0, 0]), int(batch["policy/version"])))
        if i == 2:
            with torch.no_grad(), simloader.policy.updating(policy):
                policy.bias.fill_(-0.5)
    assert seen[0] == (0.5, 0) and seen[-1] == (-0.5, 1)
    assert all(version == (value < 0) for value, version in seen)


def batches_while_training(policy, update, step, num_batches):
    """The batches of a cart-pole closed loop on `policy`, simulated while a trainer thread
    calls `update(value)` with a growing value, every half millisecond."""
    import threading
    import time
    stop = threading.Event()

    def train():
        value = 0.0
        while not stop.is_set():
            value += step
            update(value)
            time.sleep(0.0005)

    trainer = threading.Thread(target=train)
    trainer.start()
    try:
        ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=20,
                                  policy=policy, record=("qpos",), nthread=1,
                                  num_batches=num_batches)
        return list(ds)
    finally:
        stop.set()
        trainer.join()


def test_a_batch_runs_one_version_of_the_weights():
    """A trainer thread updates the weights all the time while batches are simulated: every
    batch's controls come from one version of the weights, the one `policy/version` names."""
    import time

    class SlowBias(Bias):
        def forward(self, obs):
            time.sleep(0.002)  # a batch spans many updates
            return super().forward(obs)

    policy = SlowBias()

    def update(value):
        with torch.no_grad():
            policy.bias.fill_(value)  # one in-place update: one version

    # steps within the ctrlrange: no clamp hides a change
    batches = batches_while_training(policy, update, step=1e-4, num_batches=8)
    values = {}
    for b in batches:
        u = b["control"][..., 0]
        assert (u == u[0, 0]).all(), "a batch mixed several versions of the weights"
        version = int(b["policy/version"])
        values.setdefault(version, float(u[0, 0]))
        assert values[version] == float(u[0, 0])
    # the updates went on during the batches: later batches ran later weights
    assert len(values) > 1 and sorted(values) == sorted(values, key=values.get)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("impl", ["mjx", "warp"])
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
    ds = simloader.SimDataset(model, backend=impl, nbatch=64, nstep=20,
                              policy=policy, record=("qpos", "qvel"),
                              **({"compilation_cache": cache_dir} if impl == "mjx" else {}))
    next(iter(ds))  # compiles
    backend = ds.make_backend(sharding.current_shard(0))
    backend.produce(0)  # the first batch of an iterator sets its buffers up
    torch.cuda.set_sync_debug_mode("error")
    try:
        with jax.transfer_guard_device_to_host("disallow"):
            produced = backend.produce(1)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert backend.deliver(produced)["qpos"].shape == (64, 20, 2)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_device_cuda_takes_a_policy_on_the_current_cuda_device():
    """device="cuda" means the current CUDA device: a policy there ("cuda:0") is accepted
    (it was refused as "not on the dataset's device cuda")."""
    pytest.importorskip("warp")
    model, policy = cartpole_policy()
    policy.float().to("cuda")
    ds = simloader.SimDataset(model, backend="warp", nbatch=8, nstep=5, policy=policy,
                              device="cuda", num_batches=1, record=("qpos", "qvel"))
    assert next(iter(ds))["control"].device.type == "cuda"


# -- the Warp engine's closed loop (`backends/warp/`) ----------------------------------------

class Pusher(torch.nn.Module):
    """A deterministic float32 policy for the rich model's six inputs (`EVERY_INPUT`, in
    mjtState order: ctrl, qfrc_applied, xfrc_applied, eq_active, mocap_pos, mocap_quat):
    bounded controls and forces of (qpos, qvel), a mocap pose near the model's (a unit
    quaternion), the grab switched on after 0.015 s, and a torque of 1e9 on trajectory 1's ball from its fourth step on: a legal
    control (under mjMAXVAL) whose acceleration is not (it diverges, is flagged and
    restarted)."""

    def __init__(self, model, ncontrol):
        super().__init__()
        torch.manual_seed(3)
        self.lin = torch.nn.Linear(model.nq + model.nv, ncontrol)
        self.qfrc = model.nu
        self.eq = model.nu + model.nv + 6 * model.nbody
        self.register_buffer("target", torch.tensor(model.body_pos[model.body("target").id],
                                                    dtype=torch.float32))

    def forward(self, obs):
        u = 2 * torch.tanh(self.lin(torch.cat([obs["qpos"], obs["qvel"]], -1)))
        late = obs["time"] > 0.015
        quat = u[:, -4:] / u[:, -4:].norm(dim=1, keepdim=True)
        u = torch.cat([u[:, :-4], quat], dim=1)
        u[:, self.eq] = late.to(u.dtype)
        # the welded target moves a little around its model pose (a reachable pull)
        u[:, self.eq + 1:self.eq + 4] = self.target + 0.05 * u[:, self.eq + 1:self.eq + 4]
        fault = torch.zeros_like(u)
        fault[1, self.qfrc + 3] = 1e9 * late[1].to(u.dtype)  # a ball dof
        return u + fault, {"late": late}


def _warp_and_cpu(monkeypatch, model, nbatches, **kwargs):
    """The batches of the Warp engine's closed loop and of the CPU backend's on the same
    configuration: both draw initial states, parameters and noise on the host from the same
    seeds, so they differ only by float32 against float64 arithmetic."""
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")  # on a GPU: the GPU, CUDA graphs
    cpu = list(simloader.SimDataset(model, backend="cpu", num_batches=nbatches, nthread=2,
                                    **kwargs))
    if torch.cuda.is_available():
        kwargs["policy"] = kwargs["policy"].cuda()
    warp = list(simloader.SimDataset(model, backend="warp", num_batches=nbatches,
                                     **kwargs))
    return warp, cpu


def _assert_same_batches(ours, theirs, atol, rtol=0.0):
    for a, b in zip(ours, theirs):
        assert sorted(set(a) - {"overflow"}) == sorted(b)
        for key in a:
            if key == "params":
                for k in a[key]:
                    assert torch.equal(a[key][k].cpu(), b[key][k].cpu()), k
            elif key == "overflow":  # the Warp engine's alone
                continue
            elif key == "policy/version" or not a[key].is_floating_point():
                assert torch.equal(a[key].cpu(), b[key].cpu()), key
            else:
                np.testing.assert_allclose(a[key].cpu().numpy(), b[key].cpu().numpy(),
                                           atol=atol, rtol=rtol, err_msg=key)


def test_warp_closed_loop_follows_the_cpu_continuing_randomized(monkeypatch):
    """The Warp engine's closed loop computes what the CPU backend's does, in float32: reset,
    randomized damping, MuJoCo's clamp, frames every 2nd step of a state, fields and
    sensors, continuation."""
    pytest.importorskip("mujoco_warp")
    model, policy = cartpole_policy()
    policy.float()
    ours, theirs = _warp_and_cpu(
        monkeypatch, model, 2, dtype=torch.float32, nbatch=4, nstep=8, record_every=2,
        record=("state", "qpos", "qvel", "xpos", "qacc", "sensor:pole_angle", "sensordata"),
        policy=policy, continue_episodes=True,
        randomize=[dr.scale("dof_damping", dr.Uniform(50.0, 200.0))], seed=5,
        initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    _assert_same_batches(ours, theirs, atol=2e-3)
    first, second = ours
    assert first["qpos"].shape == (4, 4, 2) and first["policy/value"].shape == (4, 8)
    assert np.abs(first["control"].cpu().numpy()).max() == 1.0  # clamped where MuJoCo clamps
    assert torch.equal(second["initial_state"], first["state"][:, -1])  # continued


def test_warp_closed_loop_noise_is_drawn_on_the_device_per_batch(monkeypatch):
    """Exploration noise around a policy that says 0: the applied controls are the noise
    (drawn by torch on the simulation's device), N(0, 0.3) clipped to the ctrlrange, fresh
    every batch and the same for the same seed."""
    pytest.importorskip("mujoco_warp")
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")

    def still(obs):
        return torch.zeros(obs["state"].shape[0], 1, device=obs["state"].device)

    kwargs = dict(backend="warp", nbatch=64, nstep=20, policy=still,
                  policy_noise=controls.Normal(std=0.3), num_batches=2, seed=9)
    first, second = list(simloader.SimDataset("cartpole", **kwargs))
    again = next(iter(simloader.SimDataset("cartpole", **kwargs)))
    u = first["control"].cpu().numpy()
    assert abs(u.std() - 0.3) < 0.03 and abs(u.mean()) < 0.03 and np.abs(u).max() <= 1.0
    assert not torch.equal(first["control"], second["control"])
    assert torch.equal(first["control"], again["control"])


def test_warp_closed_loop_follows_the_cpu_on_contacts_every_input_and_a_fault(
        monkeypatch, rich_model):
    """Contacts (the ball on the floor), every control_spec input, and a trajectory driven
    to divergence: flagged, restarted, and the others as the CPU backend has them; every 4th
    step recorded."""
    pytest.importorskip("mujoco_warp")
    spec = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED | S.mjSTATE_XFRC_APPLIED
               | S.mjSTATE_MOCAP_POS | S.mjSTATE_MOCAP_QUAT | S.mjSTATE_EQ_ACTIVE)
    m = rich_model
    policy = Pusher(m, mujoco.mj_stateSize(m, spec))
    ours, theirs = _warp_and_cpu(
        monkeypatch, m, 1, nbatch=3, nstep=12, record_every=4, control_spec=spec,
        policy=policy, dtype=torch.float32,
        record=("time", "qpos", "qvel", "qfrc_constraint", "sensordata"), seed=1)
    # compared over the first frame (4 steps, the grab engaging at the last): beyond it the
    # weld's stiff transient parts float32 from float64 by about 1% in velocity, which the
    # policy's feedback then amplifies; the diverged trajectory restarts where each engine's
    # check fires (MuJoCo's mid-step), so it is left out
    def first_frame(b):
        return {k: (v if k in ("params", "policy/version") else
                    v[[0, 2]] if v.ndim == 1 else
                    v[[0, 2]][:, :4] if k in ("control", "policy/late") else v[[0, 2]][:, :1])
                for k, v in b.items()}
    _assert_same_batches([first_frame(b) for b in ours], [first_frame(b) for b in theirs],
                         atol=1e-4)
    (batch,) = ours
    assert batch["qpos"].shape == (3, 3, m.nq) and batch["control"].shape[1] == 12
    assert batch["diverged"].tolist() == [False, True, False]
    assert torch.isfinite(batch["qpos"]).all()  # restarted, never NaN
    assert (batch["qfrc_constraint"][0, :, :6].abs().sum() > 0).item()  # the ball is on the floor


def test_warp_closed_loop_renders_what_the_open_loop_renders(monkeypatch):
    """A policy that sees a camera: the Warp engine renders after every step, restarts
    included; replaying the controls it chose open loop gives the same images and states."""
    pytest.importorskip("mujoco_warp")
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")

    class Looks(torch.nn.Module):
        """Pushes the cart by how much of the image is lit, and keeps what it saw."""

        def forward(self, obs):
            rgb = obs["camera/front/rgb"].float().mean(dim=(1, 2, 3))
            u = torch.tanh(rgb[:, None] / 64 - 1 + obs["qvel"][:, :1])
            return u, {"depth": obs["camera/front/depth"].mean(dim=(1, 2))}

    camera = simloader.Camera("front", height=16, width=24, depth=True, segmentation=True)
    kwargs = dict(backend="warp", nbatch=3, nstep=6, seed=3, dtype=torch.float32,
                  record=("qpos", "qvel", camera), num_batches=1,
                  initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    (a,) = list(simloader.SimDataset("cartpole", policy=Looks(), **kwargs))
    (b,) = list(simloader.SimDataset("cartpole", control=a["control"].cpu(), **kwargs))
    assert a["camera/front/rgb"].dtype == torch.uint8 and a["camera/front/rgb"].float().mean() > 10
    assert (a["camera/front/segmentation"] >= 0).any()
    for key in ("qpos", "qvel", "camera/front/rgb", "camera/front/depth",
                "camera/front/segmentation"):
        assert torch.equal(a[key], b[key]), key
    assert a["policy/depth"].shape == (3, 6)


class TwoHalves(torch.nn.Module):
    """Control = a + b over two parameters, which an update changes one after the other."""

    def __init__(self):
        super().__init__()
        self.a = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64))
        self.b = torch.nn.Parameter(torch.zeros(1, dtype=torch.float64))

    def forward(self, obs):
        return (self.a - self.b).expand(obs["qpos"].shape[0], 1)


@pytest.mark.parametrize("counter", ["torch", "int", "buffer"])
def test_updating_keeps_half_updates_out_of_batches(counter):
    """A trainer thread updates two tensors with a pause between them, inside
    `simloader.policy.updating`: no batch copies one tensor's update without the other's
    (control a - b stays 0), and each version names one pair of values."""
    import time
    policy = TwoHalves()
    if counter == "int":
        policy.version = 0
    elif counter == "buffer":
        policy.register_buffer("version", torch.zeros((), dtype=torch.int64))

    def update(value):
        with torch.no_grad(), simloader.policy.updating(policy):
            policy.a.fill_(value)
            time.sleep(0.002)  # the half-done update lasts long enough to be copied
            policy.b.fill_(value)

    batches = batches_while_training(policy, update, step=1e-3, num_batches=12)
    versions = [int(b["policy/version"]) for b in batches]
    assert all((b["control"] == 0).all() for b in batches), "a batch copied half an update"
    assert versions == sorted(versions) and len(set(versions)) > 1 and min(versions) >= 0


def test_an_update_left_open_is_reported(monkeypatch):
    monkeypatch.setattr(simloader.policy, "UPDATE_WAIT_S", 0.2)
    policy = TwoHalves()
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=3,
                              policy=policy, record=("qpos",), nthread=1, num_batches=1)
    with simloader.policy.updating(policy):
        with pytest.raises(RuntimeError, match="inside an update"):
            next(iter(ds))
    assert int(next(iter(ds))["policy/version"]) == simloader.policy.version(policy)
