"""`deterministic=` and `sim_device=`: the CPU side (arguments, refusals with their reasons,
the rule each engine promises bit-identical batches by, and a batch split in parts, simulated
on JAX's CPU device twice). The GPU side is in tests/test_placement_gpu.py (marker `gpu`)."""

import json

import mujoco
import numpy as np
import pytest
import torch

import simloader
from simloader import controls, initial
from simloader.backends import auto, contract, warp
from simloader.backends.warp import determinism
from simloader.config import split_sizes
from simloader.terminate import Outside, TimeLimit

pytest.importorskip("mujoco.mjx")


def cpu_dataset(**kwargs):
    kwargs = {"backend": "cpu", "nbatch": 8, "nstep": 5, "num_batches": 2,
              "control": controls.Uniform(), **kwargs}
    return simloader.SimDataset("cartpole", **kwargs)


# -- deterministic= -----------------------------------------------------------------------

def test_deterministic_follows_torch_by_default():
    assert cpu_dataset().config.deterministic is False
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        assert cpu_dataset().config.deterministic is True
        assert cpu_dataset(deterministic=False).config.deterministic is False
    finally:
        torch.use_deterministic_algorithms(before)


def test_deterministic_cpu_engine_is_bit_identical():
    assert "deterministic: bit-identical batches" in cpu_dataset(deterministic=True).describe()
    a, b = (list(cpu_dataset(deterministic=True, seed=4)) for _ in range(2))
    assert all(torch.equal(x[k], y[k]) for x, y in zip(a, b) for k in x)


@pytest.mark.parametrize("bad", ["yes", 1, 0.0])
def test_deterministic_must_be_a_bool(bad):
    with pytest.raises(TypeError, match=r"deterministic: expected None .*True or False"):
        cpu_dataset(deterministic=bad)


def test_warp_refused_by_name_for_a_contact_model():
    # refused from the model alone, before Warp (or a GPU) is looked for
    with pytest.raises(ValueError, match=r"deterministic: backend='warp' cannot give "
                                         r"bit-identical batches .*contacts.*backend='mjx'"):
        simloader.SimDataset("humanoid", backend="warp", nbatch=4, nstep=2,
                             deterministic=True)


def test_warp_rule_on_models():
    assert determinism.refusal(simloader.load_model("cartpole")) is None
    humanoid = simloader.load_model("humanoid")
    assert "contacts" in determinism.refusal(humanoid)
    humanoid.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    said = determinism.refusal(humanoid)  # its 21 limited hinges race for rows
    assert "contacts" not in said and "21 limited slide or hinge joints" in said
    humanoid.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT
    assert determinism.refusal(humanoid) is None
    tendons = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><body>
      <joint name="a" type="hinge"/><geom size=".1" contype="0" conaffinity="0"/>
      <body><joint name="b" type="hinge"/><geom size=".1" contype="0" conaffinity="0"/>
      </body></body></worldbody>
      <tendon><fixed name="t"><joint joint="a" coef="1"/><joint joint="b" coef="1"/></fixed>
      </tendon></mujoco>""")
    assert "1 tendons" in determinism.refusal(tendons)


def test_auto_chooses_only_engines_that_promise_it():
    humanoid = simloader.load_model("humanoid")
    probe = type("Probe", (), dict(model=humanoid, nbatch=8192, nstep=100, num_batches=None,
                                   observations=(), policy=None, deterministic=True))
    choice = auto.choose("auto", False, probe)
    assert choice.backend != "warp"
    if warp.entry.ENGINE.missing() is None:  # where Warp could run, the reason says why not
        assert "deterministic=True" in choice.reason


def test_outside_engine_promises_nothing_by_default():
    class Outside(contract.EngineEntry):
        name = "outside"
    assert "does not promise bit-identical" in Outside().refuses_determinism(None)


def test_mjx_sets_xla_deterministic_ops_before_jax_starts(fresh_python):
    script = """
import json, os, simloader
ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2, deterministic=True)
print(json.dumps({"flags": os.environ.get("XLA_FLAGS", ""),
                  "deterministic": ds.config.deterministic}))
"""
    (out,) = fresh_python(script, [([], {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"})])
    said = json.loads(out.strip().splitlines()[-1])
    assert said["deterministic"] is True
    assert said["flags"].split() == ["--xla_cpu_enable_fast_math=false",
                                     "--xla_gpu_deterministic_ops=true"]


# -- sim_device= --------------------------------------------------------------------------

@pytest.mark.parametrize("sim_device, match", [
    ("cuda:1", r"sim_device: 'cuda:1' requested but torch sees no CUDA device"),
    (["cpu", "tpu"], r"sim_device\[1\]: expected 'cpu', 'cuda' or 'cuda:N', got 'tpu'"),
    (["cpu", None], r"sim_device\[1\]: expected 'cpu', 'cuda' or 'cuda:N', got None"),
    ("mps", r"sim_device: expected a cpu or cuda device, got 'mps'"),
    ([], r"sim_device: expected a device or a non-empty sequence"),
])
def test_sim_device_bad_values(sim_device, match):
    if torch.cuda.is_available() and "cuda" in str(sim_device):
        pytest.skip("this machine has a GPU")
    with pytest.raises(ValueError, match=match):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=4, nstep=2,
                             sim_device=sim_device)


def test_sim_device_refused_by_the_cpu_engine():
    with pytest.raises(ValueError, match=r"sim_device: the CPU engine simulates on the CPU's "
                                         r"threads \(nthread=\)"):
        cpu_dataset(sim_device=["cpu", "cpu"])


def test_sim_device_needs_a_trajectory_per_device():
    with pytest.raises(ValueError, match=r"sim_device: 3 simulation devices for nbatch=2"):
        simloader.SimDataset("cartpole", backend="mjx", nbatch=2, nstep=2,
                             sim_device=["cpu"] * 3)


def test_sim_device_where_delivered_is_no_split():
    ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=4, nstep=2, device="cpu",
                              sim_device="cpu")
    assert ds.config.parts is None


def test_split_sizes():
    assert split_sizes(10, 3) == [4, 3, 3]
    assert split_sizes(4, 4) == [1, 1, 1, 1]
    assert sum(split_sizes(8193, 3)) == 8193


def test_parts_take_their_rows_of_per_trajectory_arguments():
    nbatch, nstep = 5, 3
    x0 = np.arange(nbatch)[:, None] * np.ones((1, 5)) * 0.01
    u = np.linspace(-1, 1, nbatch * nstep).reshape(nbatch, nstep, 1)
    ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=nbatch, nstep=nstep,
                              device="cpu", sim_device=["cpu", "cpu"], control=u,
                              initial_state=x0)
    first, second = ds.config.parts
    assert (first.nbatch, second.nbatch) == (3, 2)
    np.testing.assert_array_equal(second.initial.fixed, x0[3:])
    np.testing.assert_array_equal(second.control.fixed, u[3:])
    assert first.device == second.device == torch.device("cpu")
    assert "simulated on cpu, cpu (trajectories 3, 2), delivered on cpu" in ds.describe()


def run_split(make):
    """(make, the dataset, its batches, its state after the first batch) of stream `make()`."""
    ds = make()
    it = iter(ds)
    batches = [next(it)]
    state = ds.state_dict()
    batches += list(it)
    return make, ds, batches, state


@pytest.fixture(scope="module")
def split_stream():
    """A continuing MJX stream split over two parts on JAX's CPU device, 3 batches."""
    def make():
        return simloader.SimDataset(
            "cartpole", backend="mjx", nbatch=6, nstep=4, num_batches=3, seed=7, device="cpu",
            sim_device=["cpu", "cpu"], control=controls.Uniform(),
            initial_state=initial.Perturbed(), continue_episodes=True, deterministic=True)
    return run_split(make)


def test_split_batch_gathers_every_part(split_stream):
    _, ds, batches, _ = split_stream
    assert len(batches) == 3
    for b in batches:
        assert b["state"].shape == (6, 4, 5) and b["control"].shape == (6, 4, 1)
        assert b["diverged"].shape == (6,)
    # each part draws from its own stream: the two halves differ
    assert not torch.equal(batches[0]["control"][:3], batches[0]["control"][3:])
    # continuing: each trajectory starts where it ended (qpos, qvel of the FULLPHYSICS row)
    torch.testing.assert_close(batches[1]["initial_state"], batches[0]["state"][:, -1],
                               rtol=0, atol=0)
    stats = ds.stats
    assert stats["batches"] == 3 and stats["steps"] == 3 * 6 * 4
    assert "sim_parts" in ds.state_dict()["config"]


def test_split_stream_repeats_and_resumes_bit_for_bit(split_stream):
    make, _, batches, state = split_stream
    again = list(make())
    assert all(torch.equal(a[k], b[k]) for a, b in zip(batches, again) for k in a)
    resumed = make()
    resumed.load_state_dict(json.loads(json.dumps(state)))
    rest = list(resumed)
    assert len(rest) == 2
    assert all(torch.equal(a[k], b[k]) for a, b in zip(batches[1:], rest) for k in a)


def test_split_state_does_not_resume_an_unsplit_stream(split_stream):
    _, _, _, state = split_stream
    whole = simloader.SimDataset(
        "cartpole", backend="mjx", nbatch=6, nstep=4, num_batches=3, seed=7, device="cpu",
        control=controls.Uniform(), initial_state=initial.Perturbed(), continue_episodes=True)
    with pytest.raises(ValueError, match="sim_parts"):
        whole.load_state_dict(state)


def test_warp_split_in_two_parts_on_its_cpu_device_with_a_policy(monkeypatch):
    """MuJoCo Warp's kernels on its CPU device (as tests/test_warp.py runs them): a closed
    loop split in two parts, each running its own copy of the policy, twice the same."""
    pytest.importorskip("mujoco_warp")
    monkeypatch.setenv("SIMLOADER_WARP_ON_CPU", "1")
    torch.manual_seed(0)
    mlp = torch.nn.Sequential(torch.nn.Linear(5, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))

    def run():
        ds = simloader.SimDataset("cartpole", backend="warp", nbatch=6, nstep=5,
                                  num_batches=2, seed=1, device="cpu",
                                  sim_device=["cpu", "cpu"], policy=lambda o: mlp(o["state"]),
                                  initial_state=initial.Perturbed())
        return ds, list(ds)
    ds, a = run()
    _, b = run()
    assert [p.nbatch for p in ds.config.parts] == [3, 3]
    assert a[0]["state"].shape == (6, 5, 5) and a[0]["control"].shape == (6, 5, 1)
    assert all(torch.equal(x[k], y[k]) for x, y in zip(a, b) for k in x if k != "params")
    with torch.no_grad():  # the controls are the policy's, row by row
        first = mlp(a[0]["initial_state"].float()).to(a[0]["control"].dtype)
    torch.testing.assert_close(a[0]["control"][:, 0], first, rtol=1e-5, atol=1e-5)


# -- sim_device= with episodes (terminate=) -----------------------------------------------

POLE_BOUND, TIME_LIMIT = 0.2, 20


def pole_column(name="cartpole", joint="hinge"):
    """The pole joint's column in the state (FULLPHYSICS: time, then qpos)."""
    model = simloader.load_model(name)
    return 1 + int(model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT,
                                                        joint)])


def check_episodes(batches, rows, column, bound, limit, tol=1e-6):
    """Asserts the episode semantics on `rows` of a continuing stream's consecutive batches;
    returns {"terminated", "truncated", "first": counts, "carried": truncations of an episode
    that began in an earlier batch}: a terminated frame's pole angle is outside [-bound,
    bound] and every other frame's inside (within `tol`); the frame after an ending one is
    `first`, within a batch and across batches, and no other frame is; a `first` frame's
    control rows are NaN, every other frame's finite; `truncated` exactly at `limit` steps of
    an episode, counted across batches."""
    counts = dict(terminated=0, truncated=0, first=0, carried=0)
    steps, began, ended = None, None, None  # per row: steps into the episode, its batch
    for index, b in enumerate(batches):
        term, trunc, first = (b[k][rows].cpu() for k in ("terminated", "truncated", "first"))
        angle = b["state"][rows][..., column].double().cpu()
        control = b["control"][rows].cpu()
        n, nframes = term.shape
        if steps is None:  # the stream's initial state is step 0 of its first episode
            steps, began, ended = (torch.zeros(n, dtype=torch.long), torch.zeros(
                n, dtype=torch.long), torch.zeros(n, dtype=torch.bool))
        assert bool((angle[term].abs() > bound - tol).all()), "terminated inside the bounds"
        assert bool((angle[~term].abs() <= bound + tol).all()), "outside, not terminated"
        after = torch.cat([ended[:, None], (term | trunc)[:, :-1]], dim=1)
        assert torch.equal(first, after), "first is not the frame after an ending one"
        assert bool(control[first].isnan().all()), "a fresh frame's control was applied"
        assert bool(control[~first].isfinite().all()), "a stepped frame's control is NaN"
        for t in range(nframes):
            steps = torch.where(first[:, t], 0, steps + 1)
            began = torch.where(first[:, t], index, began)
            assert torch.equal(trunc[:, t], steps == limit), f"time limit at frame {t}"
            counts["carried"] += int((trunc[:, t] & (began < index)).sum())
        ended = (term | trunc)[:, -1]
        counts["terminated"] += int(term.sum())
        counts["truncated"] += int(trunc.sum())
        counts["first"] += int(first.sum())
    return counts


def same_bits(a, b):
    """Bit for bit, NaN included (a fresh frame's control rows are NaN; torch.equal says
    NaN != NaN)."""
    return a.shape == b.shape and a.dtype == b.dtype and torch.equal(
        a.contiguous().view(torch.uint8), b.contiguous().view(torch.uint8))


@pytest.fixture(scope="module")
def split_episodes():
    """A continuing MJX stream with episodes, split over two parts on JAX's CPU device, 3
    batches of 30 frames: the pole leaves [-0.2, 0.2] in each part's rows, and episodes run
    into TimeLimit(20) across batch boundaries (seed 1; checked below)."""

    def make():
        return simloader.SimDataset(
            "cartpole", backend="mjx", nbatch=6, nstep=30, num_batches=3, seed=1,
            device="cpu", sim_device=["cpu", "cpu"], control=controls.Uniform(),
            initial_state=initial.Perturbed(qvel_std=0.5), continue_episodes=True,
            deterministic=True,
            terminate=[Outside("hinge", -POLE_BOUND, POLE_BOUND), TimeLimit(TIME_LIMIT)])
    return run_split(make)


def test_split_episodes_deliver_their_flags(split_episodes):
    _, ds, batches, _ = split_episodes
    assert [p.nbatch for p in ds.config.parts] == [3, 3]
    assert len(batches) == 3
    for b in batches:
        for key in ("terminated", "truncated", "first"):
            assert b[key].shape == (6, 30) and b[key].dtype == torch.bool, key
            assert b[key].device == torch.device("cpu"), key
        assert b["state"].shape == (6, 30, 5)
    assert ds.stats["batches"] == 3 and ds.stats["steps"] == 3 * 6 * 30


@pytest.mark.parametrize("rows", [slice(0, 3), slice(3, 6)], ids=["part0", "part1"])
def test_split_episodes_obey_the_semantics_in_each_part(split_episodes, rows):
    _, _, batches, _ = split_episodes
    counts = check_episodes(batches, rows, pole_column(), POLE_BOUND, TIME_LIMIT)
    # each part's own episodes end both ways (else the checks above prove little)
    assert counts["terminated"] >= 1 and counts["truncated"] >= 1, counts


def test_split_time_limit_counts_across_batches(split_episodes):
    _, _, batches, _ = split_episodes
    counts = [check_episodes(batches, rows, pole_column(), POLE_BOUND, TIME_LIMIT)
              for rows in (slice(0, 3), slice(3, 6))]
    # episodes begun in one batch and truncated in the next, after TIME_LIMIT steps in all
    assert all(c["carried"] >= 1 for c in counts), counts
    # a time limit counted from each batch's start would truncate nowhere before frame 19
    early = [(i, t) for i, b in enumerate(batches[1:], 1)
             for t in b["truncated"].any(0).nonzero().flatten().tolist()
             if t < TIME_LIMIT - 1 and not b["first"][:, :t + 1].any()]
    assert early, "no episode carried over a batch boundary was truncated"


def test_split_episodes_repeat_and_resume_bit_for_bit(split_episodes):
    make, _, batches, state = split_episodes
    assert "sim_parts" in state["config"]
    again = list(make())
    assert len(again) == 3
    assert all(same_bits(a[k], b[k]) for a, b in zip(batches, again) for k in a)
    resumed = make()
    resumed.load_state_dict(json.loads(json.dumps(state)))
    rest = list(resumed)
    assert len(rest) == 2
    assert {"terminated", "truncated", "first"} <= set(rest[0])
    assert all(same_bits(a[k], b[k]) for a, b in zip(batches[1:], rest) for k in a)
