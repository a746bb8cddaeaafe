"""simloader in torchrl (CPU engine, the real torchrl and tensordict): the stream keys say which
stream a live batch continues, `to_tensordict` lays batches out in torchrl's keys, and windows
that torchrl's `SliceSampler` draws from a buffer the collector filled never straddle two
trajectories, with DataLoader workers and continued episodes too."""

import time

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import simloader
from simloader.terminate import Outside

# simloader.torchrl first (it imports torchrl): torchrl's own import would make "spawn" the
# default start method of this process, and the other tests' DataLoader workers spawned
pytest.importorskip("simloader.torchrl")
from simloader.torchrl import SimCollector, to_tensordict  # noqa: E402
from torchrl.data import LazyTensorStorage, ReplayBuffer, SliceSampler  # noqa: E402


def test_importing_it_leaves_the_default_start_method_as_it_was(fresh_python):
    script = ("import multiprocessing as mp, simloader.torchrl, torchrl; "
              "print(mp.get_start_method(allow_none=True))")
    assert fresh_python(script, [([], {})])[0].strip() == "None"


def cartpole(**kwargs):
    base = dict(backend="cpu", nbatch=4, nstep=20, nthread=1, seed=3,
                control=simloader.controls.Uniform())
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


def episodic(**kwargs):
    # the pole past 0.02 rad ends an episode: several per trajectory with random pushes
    return cartpole(terminate=Outside("hinge", -0.02, 0.02), **kwargs)


def test_each_row_names_its_stream_and_a_continued_batch_continues_batch_b_minus_workers():
    ds = episodic(continue_episodes=True, num_batches=6)
    batches = list(DataLoader(ds, batch_size=None, num_workers=2))
    # worker w delivers global batches w, w + 2, ...: batch b continues batch b - 2
    assert [b["stream"].tolist() for b in batches] == [[0, 1, 2, 3], [4, 5, 6, 7]] * 3
    for b in range(2, 6):
        before, now = batches[b - 2], batches[b]
        assert torch.equal(now["initial_state"], before["state"][:, -1])
        # the initial state's episode is the previous batch's last frame's
        assert torch.equal(now["episode"], before["episode"] + before["first"].sum(1))
        assert not now["initial_first"].any()
    assert all(b["initial_first"].all() for b in batches[:2])
    assert sum(int(b["first"].sum()) for b in batches) > 5  # resets happened


def test_without_continued_episodes_every_batch_starts_new_episodes():
    batches = list(episodic(num_batches=3))
    assert [b["episode"].tolist() for b in batches[:1]] == [[0] * 4]
    for before, now in zip(batches, batches[1:]):
        assert torch.equal(now["episode"], before["episode"] + before["first"].sum(1) + 1)
        assert now["initial_first"].all()


def test_trajectory_ids_are_unique_per_episode_across_batches_workers_and_resets():
    ds = episodic(continue_episodes=True, num_batches=8)
    seen = {}  # id -> (stream, episode)
    for batch in DataLoader(ds, batch_size=None, num_workers=2):
        ids = simloader.streams.trajectory_ids(batch)
        episodes = batch["episode"][:, None] + batch["first"].cumsum(1)
        for i, stream, episode in zip(ids.reshape(-1).tolist(),
                                      batch["stream"][:, None].expand_as(ids).reshape(-1).tolist(),
                                      episodes.reshape(-1).tolist()):
            assert seen.setdefault(i, (stream, episode)) == (stream, episode)
        # a new id exactly where a fresh frame starts an episode
        changed = ids[:, 1:] != ids[:, :-1]
        assert torch.equal(changed, batch["first"][:, 1:])
    assert len(seen) > 2 * 4


def test_to_tensordict_lays_a_batch_out_in_torchrls_keys():
    batch = next(iter(episodic(num_batches=1, nstep=40)))
    td = to_tensordict(batch)
    assert td.batch_size == torch.Size([4, 40])
    assert torch.equal(td["observation"][:, 0], batch["initial_state"])
    assert torch.equal(td["observation"][:, 1:], batch["state"][:, :-1])
    assert td["next", "observation"].data_ptr() == batch["state"].data_ptr()  # a view
    assert td["action"].data_ptr() == batch["control"].data_ptr()  # a view
    assert torch.equal(td["action"].nan_to_num(7.0), batch["control"].nan_to_num(7.0))
    for key in ("terminated", "truncated"):
        assert torch.equal(td["next", key][..., 0], batch[key])
    assert torch.equal(td["next", "done"][..., 0], batch["terminated"] | batch["truncated"])
    assert td["is_init"][:, 0].all() and torch.equal(td["is_init"][:, 1:, 0], batch["first"][:, :-1])
    mask = td["collector", "mask"]
    assert torch.equal(mask, ~batch["first"])
    assert (~mask).any(), "no reset happened: the test shows nothing"
    ids = td["collector", "traj_ids"]
    assert (ids[mask] >= 0).all() and (ids[~mask] < 0).all()
    # inside a trajectory, ("next", "observation") at t is the observation at t + 1
    same = (ids[:, 1:] == ids[:, :-1])
    assert torch.equal(td["next", "observation"][:, :-1][same], td["observation"][:, 1:][same])
    # the non-physics rows have ids of their own
    assert len(set(ids[~mask].tolist())) == int((~mask).sum())
    assert not set(ids[~mask].tolist()) & set(ids[mask].tolist())


def test_observations_without_an_initial_value_start_at_frame_0():
    ds = cartpole(num_batches=1, record=["state", "sensordata"])
    batch = next(iter(ds))
    td = to_tensordict(batch, {"state": "observation", "sensordata": "sensors"})
    assert td.batch_size == torch.Size([4, 19])
    assert torch.equal(td["sensors"], batch["sensordata"][:, :-1])
    assert torch.equal(td["next", "sensors"], batch["sensordata"][:, 1:])
    assert torch.equal(td["action"], batch["control"][:, 1:])
    assert not td["is_init"].any()
    with pytest.raises(KeyError, match="observation: the batch has no key 'qpos'"):
        to_tensordict(batch, "qpos")


def test_a_diverged_trajectory_is_masked_out():
    batch = dict(next(iter(episodic(num_batches=1))))
    batch["diverged"] = torch.tensor([False, True, False, False])
    td = to_tensordict(batch)
    assert not td["collector", "mask"][1].any()
    assert (td["collector", "traj_ids"][1] < 0).all()


@pytest.mark.parametrize("workers", [0, 2])
def test_slice_sampler_windows_from_the_collector_never_straddle_two_trajectories(workers):
    ds = episodic(continue_episodes=True, num_batches=12, nstep=30, nbatch=3)
    collector = SimCollector(ds, num_workers=workers)
    length = 6
    rb = ReplayBuffer(storage=LazyTensorStorage(10_000),
                      sampler=SliceSampler(slice_len=length, strict_length=True,
                                           traj_key=("collector", "traj_ids")),
                      batch_size=length * 64)
    # every physics step simulated: (observation, action, next observation) -> its trajectory
    steps = {}
    for td in collector:
        for row in td[td["collector", "mask"]].unbind(0):
            key = (row["observation"].numpy().tobytes(), row["action"].numpy().tobytes())
            steps[key] = (row["next", "observation"].numpy().tobytes(),
                          int(row["collector", "traj_ids"]))
        rb.extend(td[td["collector", "mask"]])
    assert len(rb) == len(steps)
    for _ in range(5):
        windows = rb.sample().reshape(-1, length)
        for w in windows.unbind(0):
            ids = w["collector", "traj_ids"]
            assert (ids == ids[0]).all()
            for t in range(length):
                key = (w["observation"][t].numpy().tobytes(), w["action"][t].numpy().tobytes())
                assert steps[key] == (w["next", "observation"][t].numpy().tobytes(), int(ids[0]))
            # one trajectory: each step starts where the previous ended
            assert torch.equal(w["next", "observation"][:-1], w["observation"][1:])
            assert not w["is_init"][1:].any()
            assert torch.equal(w["next", "done"], w["next", "terminated"] | w["next", "truncated"])


def test_the_collector_resumes_where_its_state_was_saved():
    make = lambda: SimCollector(episodic(continue_episodes=True, num_batches=5))  # noqa: E731
    first = make()
    it = iter(first)
    next(it), next(it)
    state = first.state_dict()
    rest = [td.clone() for td in it]
    again = make()
    again.load_state_dict(state)
    resumed = list(again)
    assert len(resumed) == len(rest) == 3
    for a, b in zip(rest, resumed):  # traj ids included: the stream keys resume their counters
        assert set(a.keys(True, True)) == set(b.keys(True, True))
        for key in a.keys(True, True):
            torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, equal_nan=True)


def test_set_seed_starts_the_stream_of_another_seed():
    collector = SimCollector(cartpole(num_batches=1))
    a = next(iter(collector))["next", "observation"].clone()
    assert collector.set_seed(7) == 7
    b = next(iter(collector))["next", "observation"]
    assert not torch.equal(a, b)
    assert torch.equal(b, next(iter(cartpole(num_batches=1, seed=7)))["state"])


class Push(torch.nn.Module):
    """A constant push, its weight the force: the control names the weights that acted."""

    def __init__(self):
        super().__init__()
        self.force = torch.nn.Parameter(torch.zeros((), dtype=torch.float64))

    def forward(self, obs):
        return self.force.expand(len(obs["state"]), 1)


@pytest.mark.parametrize("workers", [0, 2])
def test_update_policy_weights_reaches_the_batches_within_the_stated_staleness(workers):
    policy = Push()
    if workers:  # what workers see of the training process's updates: shared memory
        policy.register_buffer("version", torch.zeros((), dtype=torch.int64))
        policy.share_memory()
    ds = cartpole(control=None, policy=policy, prefetch=1, nstep=4)
    batches = 12 + 8 * workers
    collector = SimCollector(ds, total_frames=4 * 4 * batches, num_workers=workers,
                             multiprocessing_context="fork" if workers else None)
    assert collector.staleness == (2 if not workers else 2 * (1 + 1 + 2))
    start = simloader.policy.version(policy)
    lags = []
    for updates, td in enumerate(collector):
        time.sleep(0.05)  # a learner slower than the simulator: the producers run ahead
        acted = int(td["policy_version"][0, 0]) - start  # the updates its weights had
        assert torch.all(td["action"] == acted / 100)  # and it acted with exactly those
        lags.append(updates - acted)
        trained = Push()
        with torch.no_grad():
            trained.force.fill_((updates + 1) / 100)
        collector.update_policy_weights_(trained)
    assert len(lags) == batches
    assert max(lags) <= collector.staleness
    assert max(lags) == collector.staleness  # the bound is reached: it is the real one
    with pytest.raises(ValueError, match="no policy="):
        SimCollector(cartpole(num_batches=1)).update_policy_weights_(Push())


def test_a_mixtures_streams_are_unique_across_its_members():
    mix = simloader.Mixture({"a": cartpole(), "b": cartpole(seed=9)}, seed=1)
    seen = {}
    for i, batch in zip(range(6), mix):
        for stream in batch["stream"].tolist():
            assert seen.setdefault(stream, int(batch["task"])) == int(batch["task"])
    assert sorted(seen) == list(range(8))


def test_a_collector_over_a_mixture_updates_every_members_policy():
    policy = Push()
    members = {"a": cartpole(control=None, policy=policy, prefetch=1, nstep=4),
               "b": cartpole(control=None, policy=policy, prefetch=1, nstep=4, seed=8)}
    collector = SimCollector(simloader.Mixture(members, seed=2), total_frames=4 * 4 * 16)
    assert collector.staleness == 2  # per member: its own batches begun ahead
    trained = Push()
    with torch.no_grad():
        trained.force.fill_(0.5)
    since = {0: 0, 1: 0}  # each member's batches delivered since the update
    for k, td in enumerate(collector):
        task = int(td["task"][0, 0])
        if k == 0:
            collector.update_policy_weights_(trained)
            continue
        since[task] += 1
        if since[task] > collector.staleness:
            assert torch.all(td["action"] == 0.5), (k, task)
    assert min(since.values()) > collector.staleness  # both members showed it
    with pytest.raises(KeyError, match="no weight 'bias'"):
        collector.update_policy_weights_({"bias": torch.zeros(())})
