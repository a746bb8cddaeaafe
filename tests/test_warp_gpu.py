"""The Warp engine inside training loops on the same GPU (marker `gpu`, run on the GPU machine).

Every row of what users hit with the Warp path through MJX (a `torch.cuda.synchronize()` every
step, a validation dataset read alternately, a JAX dataset beside a Warp one, open and closed
loop alternately) must run without error, and graphs are captured once per dataset, never
again (`stats["graph_captures"]`). Sizes are small; the humanoid has contacts and a constraint
solver, the kernels that once broke.
"""

import threading
import warnings

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

import simloader
from conftest import FAR_SITE_X0, FAR_SITE_XML, assert_far_site_restarts
from simloader import controls

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]
pytest.importorskip("mujoco_warp")

ONE_STEP_TOL = 1e-4  # one step of a contact model against MuJoCo C, state, absolute
# float32 contact physics has outliers: a trajectory near a contact's onset can move by O(1)
# in one step where float64 does not (seen on the GPU and on Warp's CPU kernels alike, the
# same trajectories each run). Wrong inputs move every trajectory, so a batch may hold at
# most this share of trajectories beyond ONE_STEP_OUTLIER_TOL, and its median must hold
# ONE_STEP_TOL.
ONE_STEP_OUTLIER_TOL = 1e-3
ONE_STEP_OUTLIERS = 1 / 16


def warp_dataset(model="humanoid", nbatch=256, nstep=20, **kwargs):
    kwargs.setdefault("control", None if "policy" in kwargs else controls.Uniform())
    return simloader.SimDataset(model, backend="warp", nbatch=nbatch, nstep=nstep,
                                **kwargs)


def assert_first_step_is_mujocos(model, batch):
    """A one-step batch agrees with MuJoCo C from its own initial states and controls: the
    median trajectory within ONE_STEP_TOL, at most ONE_STEP_OUTLIERS of them beyond
    ONE_STEP_OUTLIER_TOL."""
    x0 = batch["initial_state"].cpu().numpy().astype(np.float64)
    u = batch["control"].cpu().numpy().astype(np.float64)
    state, _ = rollout.rollout(model, mujoco.MjData(model), x0, u,
                               control_spec=int(mujoco.mjtState.mjSTATE_CTRL))
    error = np.abs(batch["state"].cpu().numpy() - state).max(axis=(1, 2))
    outliers = np.nonzero(error > ONE_STEP_OUTLIER_TOL)[0]
    assert np.median(error) <= ONE_STEP_TOL, f"median error {np.median(error):.3g}"
    assert len(outliers) <= len(error) * ONE_STEP_OUTLIERS, (
        f"{len(outliers)} of {len(error)} trajectories off MuJoCo C by more than "
        f"{ONE_STEP_OUTLIER_TOL}: {dict(zip(outliers.tolist(), error[outliers].tolist()))}")


def trainer(nin, nout=8):
    model = torch.nn.Sequential(torch.nn.Linear(nin, 128), torch.nn.ReLU(),
                                torch.nn.Linear(128, nout)).cuda()
    return model, torch.optim.Adam(model.parameters(), 1e-3)


def train_step(model, opt, x, i):
    """A step of a training loop that does what trainers do: loss.item(), a host sync,
    tensors of new shapes every step, empty_cache now and then."""
    x = x.reshape(-1, x.shape[-1])[: 1000 + 17 * i].float()
    loss = model(x).pow(2).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    assert torch.isfinite(torch.tensor(loss.item()))
    torch.cuda.synchronize()
    torch.zeros(1 + i, 3 + i % 5, device="cuda").sum()
    if i % 10 == 0:
        torch.cuda.empty_cache()


def test_a_training_loop_that_synchronizes_every_step():
    ds = warp_dataset(num_batches=30)
    model, opt = trainer(ds.config.nstate)
    for i, batch in enumerate(ds):
        assert not batch["diverged"].all()
        train_step(model, opt, batch["state"], i)
    assert ds.stats["graph_captures"] == 1 and ds.stats["batches"] == 30


def test_an_engine_built_while_another_queues_batches_steps_right():
    """Engines built (first step, graph capture) while another dataset's producer queues
    batches in another thread: each new engine's step agrees with MuJoCo C. Warp's current
    stream belongs to the process; scoped by two threads at once, a build's kernels ran on
    the other engine's stream, or escaped its capture."""
    busy = warp_dataset("cartpole", nbatch=64, nstep=5, num_batches=10**6)
    stop, failed = threading.Event(), []

    def consume():
        try:
            for batch in busy:
                if stop.is_set():
                    return
        except Exception as e:  # noqa: BLE001 (reported in the main thread)
            failed.append(e)

    reader = threading.Thread(target=consume)
    reader.start()
    model = simloader.load_model("humanoid")
    try:
        for seed in range(3):  # a new configuration each: a new engine, built now
            ds = warp_dataset(model, nbatch=64, nstep=1, seed=seed, num_batches=1)
            assert_first_step_is_mujocos(model, next(iter(ds)))
    finally:
        stop.set()
        reader.join()
    assert not failed, failed


def test_a_busy_default_stream_does_not_reach_a_batchs_inputs():
    """The consumer's work queued on the default stream (a training step's kernels, not
    waited for) does not delay a batch's inputs past the reset that reads them: every batch
    starts from the initial states the CPU backend draws from the same seeds, and its first
    step agrees with MuJoCo C. (The inputs were once uploaded on the producer thread's
    default stream, which the engine's stream does not wait on.)"""
    model = simloader.load_model("humanoid")
    kwargs = dict(nbatch=64, nstep=1, num_batches=6, control=controls.Uniform(),
                  initial_state=simloader.initial.Perturbed(qvel_std=0.5))
    drawn = simloader.SimDataset(model, backend="cpu", **kwargs)
    a = torch.randn(4096, 4096, device="cuda")

    def busy():  # about a hundred milliseconds of matmuls, queued, not waited for
        for _ in range(50):
            a.copy_(torch.tanh(a @ a))

    busy()
    for batch, on_cpu in zip(warp_dataset(model, **kwargs), drawn):
        busy()
        np.testing.assert_allclose(batch["initial_state"].cpu().numpy(),
                                   on_cpu["initial_state"].numpy(), rtol=1e-6, atol=1e-6)
        assert_first_step_is_mujocos(model, batch)


def test_train_and_validation_datasets_read_alternately_over_epochs():
    train = warp_dataset(nbatch=512, num_batches=12)
    valid = warp_dataset(nbatch=128, nstep=10, num_batches=4, seed=1)
    model, opt = trainer(train.config.nstate)
    for epoch in range(2):
        it = iter(valid)
        for i, batch in enumerate(train):
            train_step(model, opt, batch["state"], i)
            if i % 3 == 0:
                with torch.no_grad():
                    model(next(it)["state"].reshape(-1, train.config.nstate)).mean().item()
    assert train.stats["graph_captures"] == 1 and valid.stats["graph_captures"] == 1


def test_a_jax_dataset_and_a_warp_dataset_alternately():
    pytest.importorskip("mujoco.mjx")
    jax_ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=256, nstep=20,
                                  control=controls.Uniform(), num_batches=10)
    warp_ds = warp_dataset(num_batches=10)
    model, opt = trainer(warp_ds.config.nstate)
    for i, (a, b) in enumerate(zip(jax_ds, warp_ds)):
        assert a["state"].is_cuda and b["state"].is_cuda
        train_step(model, opt, b["state"], i)
    assert warp_ds.stats["graph_captures"] == 1


def test_a_cpu_dataset_and_a_warp_dataset_alternately():
    cpu_ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=64, nstep=20,
                                  control=controls.Uniform(), num_batches=8, nthread=2)
    warp_ds = warp_dataset(num_batches=8)
    model, opt = trainer(warp_ds.config.nstate)
    for i, (a, b) in enumerate(zip(cpu_ds, warp_ds)):
        train_step(model, opt, b["state"], i)
    assert warp_ds.stats["graph_captures"] == 1


def test_open_and_closed_loop_alternately():
    open_ds = warp_dataset(num_batches=8)
    nobs = open_ds.config.nstate
    policy = torch.nn.Sequential(torch.nn.Linear(nobs, 64), torch.nn.Tanh(),
                                 torch.nn.Linear(64, open_ds.config.model.nu)).cuda()
    closed_ds = warp_dataset(nbatch=128, policy=lambda o: policy(o["state"]), num_batches=8)
    model, opt = trainer(nobs)
    for i, (a, b) in enumerate(zip(open_ds, closed_ds)):
        train_step(model, opt, a["state"], i)
        train_step(model, opt, b["state"], i)
    assert open_ds.stats["graph_captures"] == 1 and closed_ds.stats["graph_captures"] == 1


def test_a_compiled_model_under_autocast():
    ds = warp_dataset(num_batches=10)
    model, opt = trainer(ds.config.nstate)
    compiled = torch.compile(model)
    for batch in ds:
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss = compiled(batch["state"].reshape(-1, ds.config.nstate)).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        torch.cuda.synchronize()
    assert ds.stats["graph_captures"] == 1


def test_spawned_workers_each_run_an_engine():
    # torch's rule for CUDA tensors a worker lends the main process: the main releases them
    # before the worker exits (here: each batch checked inside the loop, none kept)
    ds = warp_dataset(nbatch=128, num_batches=6)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2,
                                         multiprocessing_context="spawn")
    firsts, count = [], 0
    for batch in loader:
        state = batch["state"]
        assert state.is_cuda and torch.isfinite(state).all()
        firsts.append(state[:, 0].cpu())
        count += 1
        del batch, state
    assert count == 6
    # the workers' streams differ (seeds by worker)
    assert not torch.equal(firsts[0], firsts[1])


def test_graphs_are_captured_at_the_first_batch_only():
    ds = warp_dataset(nbatch=64, nstep=5, num_batches=3)
    assert ds.stats["graph_captures"] == 0
    for _ in range(3):  # three epochs, each a new iterator
        assert len(list(ds)) == 3
    assert ds.stats["graph_captures"] == 1


def test_delivered_tensors_survive_later_batches():
    ds = warp_dataset(nbatch=64, nstep=5, num_batches=20)
    it = iter(ds)
    kept = next(it)
    copy = {k: v.clone() for k, v in kept.items() if isinstance(v, torch.Tensor)}
    for batch in it:
        del batch
    for k, v in copy.items():
        assert torch.equal(kept[k], v), k


def test_nothing_warns_on_the_defaults():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        next(iter(warp_dataset(nbatch=64, nstep=5, num_batches=1)))


def test_continued_rows_flagged_for_a_non_finite_record_restart_on_the_gpu():
    """With `continue_episodes`, the next batch's fresh rows are the rows the last batch
    flagged: the flags must be read after the steps that write them, on the engine's stream.
    (They were once copied on the producer's stream, unordered against those steps, which
    would let a flagged row continue.) Large enough that the steps are still queued when the
    producer reaches the copy: 8192 trajectories of the far-site pendulum, whose recorded site
    position overflows float32 at some angles while the physics stays finite."""
    model = mujoco.MjModel.from_xml_string(FAR_SITE_XML.format(pos="2.6e38"))
    x0 = np.tile(FAR_SITE_X0, (1024, 1))
    batches = list(warp_dataset(model, nbatch=len(x0), nstep=200, num_batches=4, seed=3,
                                record=("state", "site_xpos"), continue_episodes=True,
                                initial_state=x0))
    assert all(b["state"].is_cuda for b in batches)
    for first, second in zip(batches, batches[1:]):
        assert_far_site_restarts(first, second, x0)
