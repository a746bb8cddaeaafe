"""Windows of T frames and whole episodes from stores (CPU engine): every step of every window
is physics or a fresh start, across a continued stream's batch seams too; the three episode-end
conventions and the two action conventions; torchrl's SliceSampler agrees; loaders resume."""

import os

import numpy as np
import pytest
import torch

import simloader
from simloader.terminate import Outside

zarr = pytest.importorskip("zarr")


def cartpole(**kwargs):
    base = dict(backend="cpu", nbatch=4, nstep=20, nthread=1, seed=5,
                control=simloader.controls.Uniform())
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


def episodic(**kwargs):
    # the pole past 0.02 rad ends an episode: several per trajectory with random pushes
    return cartpole(terminate=Outside("hinge", -0.02, 0.02), **kwargs)


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    root = tmp_path_factory.mktemp("windows")
    out = {}
    for name, ds, workers in (("plain", cartpole(), 0),
                              ("episodes", episodic(nstep=30), 0),
                              ("continued", episodic(continue_episodes=True), 0),
                              ("continued-2", episodic(continue_episodes=True), 2)):
        out[name] = simloader.write(ds, root / f"{name}.zarr", batches=4, progress=False,
                                    num_workers=workers)
    return out


def physics_steps(stored):
    """Every (state before, control, state after) step the store holds as physics: each
    trajectory's initial state to its first frame, and frame to frame where the later one is
    not a fresh start (keyed by the bytes of the state before)."""
    steps = {}
    for i in range(len(stored)):
        item = stored[i]
        states = torch.cat([item["initial_state"][None], item["state"]])
        fresh = item["first"] if "first" in item else torch.zeros(len(item["state"]), dtype=torch.bool)
        for t in range(len(item["state"])):
            if not fresh[t]:
                steps.setdefault(states[t].numpy().tobytes(), []).append(
                    (item["control"][t].numpy().tobytes(), states[t + 1].numpy().tobytes()))
    return steps


@pytest.mark.parametrize("name", ["plain", "episodes", "continued", "continued-2"])
def test_every_step_of_every_window_is_one_physics_step_or_a_fresh_start(stores, name):
    stored = simloader.StoredDataset(stores[name])
    steps = physics_steps(stored)
    windows = stored.windows(6)
    batch = windows.gather(np.arange(len(windows)))
    state, control, first = batch["state"], batch["control"], batch["first"]
    checked = 0
    for b in range(len(state)):
        for t in range(1, 6):
            if first[b, t]:
                assert torch.isnan(control[b, t]).all()
                continue
            step = (control[b, t].numpy().tobytes(), state[b, t].numpy().tobytes())
            assert step in steps.get(state[b, t - 1].numpy().tobytes(), []), (name, b, t)
            checked += 1
    assert checked > 0.5 * len(state) * 5


def test_a_continued_stream_is_read_as_one_long_rollout(tmp_path):
    """With the same control rows every batch, a continued stream of 3 batches of 10 steps is
    the rollout of 30 steps, frame for frame, bit for bit, read with 0 and 2 writer workers."""
    rng = np.random.default_rng(0)
    rows = rng.uniform(-1, 1, size=(2, 10, 1))
    reference = cartpole(nbatch=2, nstep=30, control=np.tile(rows, (1, 3, 1)), num_batches=1)
    want = next(iter(torch.utils.data.DataLoader(reference, batch_size=None)))
    want = torch.cat([want["initial_state"][:, None], want["state"]], 1)  # (2, 31, nstate)
    for workers in (0, 2):
        ds = cartpole(nbatch=2, nstep=10, control=rows, continue_episodes=True)
        path = simloader.write(ds, tmp_path / f"c{workers}.zarr", batches=3 * max(1, workers),
                               progress=False, num_workers=workers)
        episodes = simloader.StoredDataset(path).episodes()
        assert len(episodes) == 2 * max(1, workers)  # one per (worker, row) stream
        for i in range(len(episodes)):
            got = episodes[i]
            assert got["first"][0] and not got["first"][1:].any()
            row = [k for k in range(2) if torch.equal(got["state"], want[k])]
            assert row, f"stream {i} is not the long rollout of either row ({workers} workers)"
        windows = simloader.StoredDataset(path).windows(31)  # each stream exactly once
        assert len(windows) == 2 * max(1, workers)


def slice_sampler_starts(table, length):
    """The windows torchrl's SliceSampler(slice_len=length, strict_length=True) draws over
    the same episodes: their first positions, sampled until every one was seen."""
    import simloader.torchrl  # noqa: F401  (first: keeps this process's start method)
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, ReplayBuffer
    from torchrl.data.replay_buffers.samplers import SliceSampler
    first, end = table.episodes()
    episode = np.repeat(np.arange(len(first)), end - first)
    positions = np.arange(len(episode))
    buffer = ReplayBuffer(storage=LazyTensorStorage(len(episode)),
                          sampler=SliceSampler(slice_len=length, traj_key="episode",
                                               strict_length=True),
                          batch_size=length * 64)
    buffer.extend(TensorDict({"episode": torch.from_numpy(episode),
                              "position": torch.from_numpy(positions)},
                             batch_size=[len(episode)]))
    seen = set()
    for _ in range(300):
        drawn = buffer.sample()["position"].reshape(-1, length).numpy()
        assert (np.diff(drawn, axis=1) == 1).all()
        seen.update(drawn[:, 0].tolist())
    return seen


def test_inside_windows_are_torchrls_strict_slices(stores):
    pytest.importorskip("simloader.torchrl")  # first: see test_torchrl.py
    windows = simloader.StoredDataset(stores["episodes"]).windows(5, ends="inside")
    ours = set(windows._starts[0].tolist())
    assert ours == slice_sampler_starts(windows.table, 5)
    batch = windows.gather(np.arange(len(windows)))
    assert not batch["first"][:, 1:].any()  # inside one episode
    short = windows.table.episodes()
    assert len(windows) == int(np.maximum(short[1] - short[0] - 4, 0).sum())


def test_cross_windows_mark_first_exactly_at_fresh_frames(stores):
    stored = simloader.StoredDataset(stores["episodes"])
    windows = stored.windows(8)
    table = windows.table
    batch = windows.gather(np.arange(len(windows)))
    positions = windows._starts[0][:, None] + np.arange(8)
    stored_first = {i: stored[i]["first"] for i in range(len(stored))}
    for b, t in zip(*np.nonzero(np.ones((len(positions), 8), bool))):
        p = positions[b, t]
        trajectory, frame = table.trajectory[p], table.frame[p]
        want = True if frame < 0 else bool(stored_first[trajectory][frame])
        assert bool(batch["first"][b, t]) == want
    assert batch["first"][:, 1:].any(), "no window crosses an episode end: a weak test"
    assert batch["terminated"].any()


def test_pad_windows_mask_exactly_past_the_episode_end(stores):
    windows = simloader.StoredDataset(stores["episodes"]).windows(12, ends="pad")
    first, end = windows.table.episodes()
    assert len(windows) == int((end - first).sum())  # a window from every frame of each
    batch = windows.gather(np.arange(len(windows)))
    starts, limits = windows._starts
    want = starts[:, None] + np.arange(12) < limits[:, None]
    assert torch.equal(batch["mask"], torch.from_numpy(want))
    assert not batch["first"][:, 1:].any()
    assert (batch["state"][~batch["mask"]] == 0).all()
    assert (~batch["mask"]).any() and batch["mask"].all(1).any()


def test_next_actions_are_produced_ones_shifted_with_zeros_at_episode_ends(stores):
    stored = simloader.StoredDataset(stores["episodes"])
    produced = stored.windows(10, actions="produced")
    following = stored.windows(10, actions="next")
    k = np.arange(len(produced))
    a, b = produced.gather(k), following.gather(k)
    assert torch.equal(a["state"], b["state"])
    positions = produced._starts[0][:, None] + np.arange(10)
    ends = produced.table.episode_end(positions)
    inside = positions + 1 < ends
    for w, t in zip(*np.nonzero(inside[:, :-1])):
        assert torch.equal(b["control"][w, t], a["control"][w, t + 1])
    assert (b["control"][torch.from_numpy(~inside)] == 0).all()
    assert not torch.isnan(b["control"]).any()


@pytest.mark.parametrize("workers", [0, 2])
def test_a_windows_loader_resumes_mid_epoch(stores, workers):
    pytest.importorskip("torchdata")
    windows = simloader.StoredDataset(stores["episodes"]).windows(6)
    loader = windows.loader(16, seed=3, num_workers=workers)
    whole = [b["state"] for b in loader]
    again = windows.loader(16, seed=3, num_workers=workers)
    it = iter(again)
    seen = [next(it)["state"] for _ in range(3)]
    state = again.state_dict()
    del it
    resumed = windows.loader(16, seed=3, num_workers=workers)
    resumed.load_state_dict(state)
    rest = [b["state"] for b in resumed]
    assert len(seen) + len(rest) == len(whole)
    assert all(torch.equal(x, y) for x, y in zip(seen + rest, whole))
    assert sum(len(b) for b in whole) == len(windows)


def test_windows_of_other_keys_start_at_the_first_stored_frame(stores):
    stored = simloader.StoredDataset(stores["plain"])
    windows = stored.windows(4, state=("state", "sensordata"), context="initial_state")
    batch = windows.gather([0])
    item = stored[int(windows.table.trajectory[windows._starts[0][0]])]
    assert torch.equal(batch["state"][0], item["state"][:4])
    assert torch.equal(batch["sensordata"][0], item["sensordata"][:4])
    assert torch.equal(batch["initial_state"][0], item["initial_state"])
    assert batch["first"][0, 0] and torch.isnan(batch["control"][0, 0]).all()
    # a store without episodes: the flags are there, False
    assert not batch["terminated"].any() and not batch["truncated"].any()
    assert batch["terminated"].shape == (1, 4)


def test_bad_arguments_are_refused_by_name(stores):
    stored = simloader.StoredDataset(stores["plain"])
    with pytest.raises(ValueError, match=r"length: expected a positive int"):
        stored.windows(0)
    with pytest.raises(ValueError, match=r"ends: expected one of \('cross', 'inside', 'pad'\)"):
        stored.windows(4, ends="wrap")
    with pytest.raises(ValueError, match=r"actions: expected one of"):
        stored.windows(4, actions="after")
    with pytest.raises(KeyError, match=r"state: 'initial_state' is per-trajectory"):
        stored.windows(4, state="initial_state")


def test_the_cameras_of_a_window_are_its_frames_rendered(tmp_path):
    pytest.importorskip("numcodecs")
    camera = simloader.Camera("front", height=16, width=16)
    ds = cartpole(nbatch=2, nstep=6, record=("state", camera))
    path = simloader.write(ds, tmp_path / "c.zarr", batches=1, progress=False)
    streamed = simloader.StoredDataset(path)
    stored = simloader.StoredDataset(path, keys=["state"], cameras=camera)
    windows = stored.windows(4)
    batch = windows.gather(np.arange(len(windows)))
    key = "camera/front/rgb"
    positions = windows._starts[0][:, None] + np.arange(4)
    for w, t in zip(*np.nonzero(windows.table.frame[positions] >= 0)):
        p = positions[w, t]
        trajectory, frame = windows.table.trajectory[p], windows.table.frame[p]
        assert torch.equal(batch[key][w, t], streamed[int(trajectory)][key][frame])
    assert batch[key].shape == (len(windows), 4, 16, 16, 3)


def test_a_mixture_stores_windows_carry_their_task(tmp_path):
    mixture = simloader.Mixture({"a": cartpole(nbatch=2, nstep=8),
                                 "b": cartpole(nbatch=2, nstep=8, seed=9)})
    path = simloader.write(mixture, tmp_path / "m.zarr", batches=6, progress=False)
    stored = simloader.open_store(path)
    windows = stored.windows(5)
    assert len(windows) == sum(len(t.windows(5)) for t in stored.tasks.values())
    batch = windows.gather(np.arange(len(windows)))
    assert batch["state"].shape[1:] == (5, 5) and set(batch["task"].tolist()) == {0, 1}
    a = stored.tasks["a"].windows(5)
    assert torch.equal(batch["state"][:len(a)], a.gather(np.arange(len(a)))["state"])
    seen = sum(len(b["task"]) for b in windows.loader(7, seed=1))
    assert seen == len(windows)


def test_a_diverged_trajectory_is_in_no_window_and_cuts_its_stream(tmp_path):
    control = np.zeros((3, 5, 1))
    control[1, 2] = np.inf  # row 1 of every batch diverges
    plain = cartpole(nbatch=3, nstep=5, control=control)
    path = simloader.write(plain, tmp_path / "d.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path)
    windows = stored.windows(3, context="diverged")
    assert len(windows) == 4 * 4  # 4 kept trajectories of 6 frames: 4 windows each
    assert not windows.gather(np.arange(len(windows)))["diverged"].any()
    kept = stored.windows(3, diverged="keep")
    assert len(kept) == 6 * 4
    continued = cartpole(nbatch=3, nstep=5, control=control, continue_episodes=True)
    path = simloader.write(continued, tmp_path / "c.zarr", batches=3, progress=False)
    table = simloader.StoredDataset(path).windows(3).table
    first, end = table.segments()
    # rows 0 and 2 run on as one stream each (16 frames); row 1's batches are all left out
    assert sorted((end - first).tolist()) == [16, 16]
    # kept, row 1's batches are not joined: each restarted afresh after its diverged one
    table = simloader.StoredDataset(path).windows(3, diverged="keep").table
    first, end = table.segments()
    assert sorted((end - first).tolist()) == [6, 6, 6, 16, 16]


def test_a_continued_stream_missing_a_batch_is_cut_there(tmp_path):
    ds = cartpole(nbatch=2, nstep=5, continue_episodes=True)
    path = simloader.write(ds, tmp_path / "c.zarr", batches=4, progress=False)
    mark = os.path.join(path, "provenance", "written", "c", "1")
    os.unlink(mark)  # batch 1 not committed (a store still being written looks so)
    windows = simloader.StoredDataset(path).windows(3)
    first, end = windows.table.segments()
    # per row: batch 0 with its initial state (6 frames), then batches 2 and 3 joined, led
    # by batch 2's initial state as a fresh start (11 frames)
    assert sorted((end - first).tolist()) == [6, 6, 11, 11]
    assert windows.table.first[first].all()


def test_windows_of_a_store_recording_every_second_step(tmp_path):
    ds = cartpole(nbatch=2, nstep=10, record_every=2)
    path = simloader.write(ds, tmp_path / "e.zarr", batches=1, progress=False)
    stored = simloader.StoredDataset(path)
    batch = stored.windows(3).gather([0, 1])
    item = stored[int(stored.windows(3).table.trajectory[0])]
    assert batch["control"].shape == (2, 3, 2, 1)  # the 2 rows between two frames
    assert torch.isnan(batch["control"][0, 0]).all()  # the initial state: nothing produced it
    assert torch.equal(batch["control"][0, 1], item["control"][0:2])
    assert torch.equal(batch["state"][0, 1:], item["state"][:2])


def test_windows_of_a_key_without_values(tmp_path):
    xml = """<mujoco><worldbody><body><joint name="j" type="slide"/><geom size=".1"/>
    </body></worldbody><actuator><motor joint="j"/></actuator></mujoco>"""
    ds = simloader.SimDataset(xml, backend="cpu", nbatch=2, nstep=4, nthread=1,
                              record=("state", "sensordata"))
    path = simloader.write(ds, tmp_path / "n.zarr", batches=1, progress=False)
    batch = simloader.StoredDataset(path).windows(2, state=("state", "sensordata")).gather([0])
    assert batch["sensordata"].shape == (1, 2, 0) and batch["state"].shape[:2] == (1, 2)


def test_a_padded_mixture_stores_windows_are_padded_per_column(tmp_path):
    wide = simloader.SimDataset("gymnasium/inverted_double_pendulum", backend="cpu", nbatch=2,
                                nstep=8, nthread=1)
    mixture = simloader.Mixture({"a": cartpole(nbatch=2, nstep=8), "b": wide}, pad=True)
    path = simloader.write(mixture, tmp_path / "p.zarr", batches=3, progress=False)
    windows = simloader.open_store(path).windows(4)
    batch = windows.gather(np.arange(len(windows)))
    narrow = batch["task"] == 0
    assert batch["state"].shape[1:] == (4, 7) and batch["mask/state"].shape[1:] == (7,)
    assert not batch["mask/state"][narrow, 5:].any() and batch["mask/state"][~narrow].all()
    assert (batch["state"][narrow][..., 5:] == 0).all()
