"""Mixture: shares follow the weights, members deliver exactly their own streams, resume is
exact (workers included), workers take disjoint parts, padding and masks, refusals."""

import dataclasses
import json
import threading

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import simloader
from simloader import controls
from simloader import randomize as dr
from simloader.mixture import Mixture

# every test below is about how batches are mixed, not simulated: small, one thread


def member(model="cartpole", nbatch=4, nstep=5, seed=0, **kwargs):
    return simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep, nthread=1,
                                control=controls.Uniform(), seed=seed,
                                initial_state=simloader.initial.Perturbed(), **kwargs)


def three(num_batches=None, continue_episodes=False, record=("state", "xpos")):
    """Three members that differ in model, size, seed, recording (the second records
    `record`) and randomization."""
    return {
        "pole": member(seed=1, num_batches=num_batches, continue_episodes=continue_episodes,
                       randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole")]),
        "other_pole": member(nbatch=3, seed=2, num_batches=num_batches,
                             record=record),
        "humanoid": member("humanoid", nbatch=2, seed=3, num_batches=num_batches,
                           continue_episodes=continue_episodes),
    }


def take(iterable, n=None):
    """The first n items (all if None), each batch's tensors cloned."""
    out = []
    for batch in iterable:
        out.append(clone(batch))
        if n is not None and len(out) == n:
            break
    return out


def clone(batch):
    return {k: (clone(v) if isinstance(v, dict) else v.clone()) for k, v in batch.items()}


def assert_same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            assert_same(a[k], b[k])
        else:
            assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


def without_task(batch, ntasks=3):
    """The member's own batch: no task, and its own stream ids (a mixture's are made unique
    across the members: member id * ntasks + task)."""
    out = {k: v for k, v in batch.items() if k != "task"}
    task = int(batch["task"])
    assert ((batch["stream"] - task) % ntasks == 0).all()
    out["stream"] = (batch["stream"] - task) // ntasks
    return out


# -- the schedule ---------------------------------------------------------------------------

@pytest.mark.parametrize("weights", [None, [1, 3], [0.2, 0.3, 0.5, 0]])
def test_shares_follow_the_weights(weights):
    n = 500
    k = 2 if weights is None else len(weights)
    members = [member(nbatch=1, nstep=1, seed=i, prefetch=1) for i in range(k)]
    tasks = [int(b["task"]) for b in take(Mixture(members, weights, seed=5), n)]
    p = np.full(k, 1 / k) if weights is None else np.asarray(weights) / sum(weights)
    counts = np.bincount(tasks, minlength=k)
    # 4 standard deviations of a binomial: fails by chance about once in 16,000 runs, and
    # this seed is fixed anyway
    assert np.all(np.abs(counts - n * p) <= 4 * np.sqrt(n * p * (1 - p))), (counts, n * p)
    for i in np.flatnonzero(p == 0):  # a member of weight 0 is never even simulated
        assert members[i].stats["batches"] == 0


def test_task_is_a_scalar_int64_index_in_dict_order():
    batches = take(Mixture({"a": member(), "b": member("humanoid", nbatch=2)}), 20)
    for b in batches:
        assert b["task"].dtype == torch.int64 and b["task"].dim() == 0
        assert b["state"].shape[-1] == (5 if int(b["task"]) == 0 else 56)
    assert {int(b["task"]) for b in batches} == {0, 1}


def test_same_seed_repeats_the_stream_and_another_seed_reorders_it():
    def run(seed):
        return take(Mixture(three(), seed=seed), 30)

    first, again, other = run(0), run(0), run(1)
    for a, b in zip(first, again):
        assert_same(a, b)
    assert [int(b["task"]) for b in first] != [int(b["task"]) for b in other]
    # a second pass over the same mixture (a new epoch) starts the stream again, as SimDataset
    mixture = Mixture(three())
    one, two = take(mixture, 10), take(mixture, 10)
    for a, b in zip(one, two):
        assert_same(a, b)


def test_each_member_delivers_exactly_its_own_stream():
    batches = take(Mixture(three(), weights=[2, 1, 1], seed=3), 40)
    alone = three()
    for i, name in enumerate(alone):
        mine = [without_task(b) for b in batches if int(b["task"]) == i]
        assert mine, name
        for got, expected in zip(mine, take(alone[name], len(mine))):
            assert_same(got, expected)


def test_members_iterators_stay_alive_and_are_closed_with_the_mixture():
    def prefetchers():
        return sum(t.name == "simloader-prefetch" and t.is_alive()
                   for t in threading.enumerate())

    before = prefetchers()
    members = three()
    it = iter(Mixture(members))
    for _ in range(12):
        next(it)
    # one producer per member drawn, kept between draws (not restarted for every batch)
    assert prefetchers() - before == 3
    produced = sum(m.stats["batches"] for m in members.values())
    assert produced <= 12 + 3 * 2  # delivered + at most `prefetch` ahead per member
    it.close()
    assert prefetchers() == before


# -- workers and ranks ---------------------------------------------------------------------

def test_workers_take_disjoint_parts_of_every_members_stream():
    n = 24
    single = take(Mixture(three(), seed=4), n)
    loader = DataLoader(Mixture(three(), seed=4), batch_size=None, num_workers=2)
    parallel = take(loader, n)
    # the schedule is a function of the seed and the position: the same under any workers
    assert [int(b["task"]) for b in parallel] == [int(b["task"]) for b in single]
    alone = three()
    for i, name in enumerate(alone):
        mine = [without_task(b) for b in parallel if int(b["task"]) == i]
        stream = take(alone[name], 2 * len(mine) + 2)
        used = []
        for got in mine:  # each delivered batch is one batch of the member's own stream...
            found = [j for j, s in enumerate(stream)
                     if all(torch.equal(got[k], s[k]) for k in ("state", "control"))]
            assert len(found) == 1, name
            used.append(found[0])
        assert len(set(used)) == len(used), name  # ...and none is delivered twice
        # worker w simulates the member's batches w, w+2, ...: both workers took part
        assert {u % 2 for u in used} == {0, 1}, (name, used)


def test_ranks_draw_their_own_member_streams_on_one_schedule(monkeypatch):
    def run(rank):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        return take(Mixture(three(), seed=6), 12)

    zero, one = run(0), run(1)
    assert [int(b["task"]) for b in zero] == [int(b["task"]) for b in one]
    assert not any(torch.equal(a["state"], b["state"]) for a in zero for b in one
                   if a["state"].shape == b["state"].shape)


# -- resuming ------------------------------------------------------------------------------

StatefulDataLoader = pytest.importorskip("torchdata.stateful_dataloader").StatefulDataLoader


def finite(pad=False):
    # continuing members: resuming must also restore where each trajectory is
    # padded: every member records the same keys (the default ones)
    members = three(num_batches=12, continue_episodes=True,
                    record=("state", "sensordata") if pad else ("state", "xpos"))
    return Mixture(members, weights=[1, 2, 1], seed=7, pad=pad)


@pytest.mark.parametrize("workers", [0, 2])
@pytest.mark.parametrize("k", [0, 1, 5, "end"])
@pytest.mark.parametrize("pad", [False, True])
def test_resume_after_k_batches_bit_for_bit(k, workers, pad):
    full = take(StatefulDataLoader(finite(pad), batch_size=None, num_workers=workers))
    assert len(full) > 5
    k = len(full) if k == "end" else k
    loader = StatefulDataLoader(finite(pad), batch_size=None, num_workers=workers)
    first = take(loader, k) if k else []
    saved = json.loads(json.dumps(loader.state_dict()))  # JSON round trip
    del loader
    resumed = StatefulDataLoader(finite(pad), batch_size=None, num_workers=workers)
    resumed.load_state_dict(saved)
    rest = take(resumed)
    assert len(first) + len(rest) == len(full)
    for a, b in zip(first + rest, full):
        assert_same(a, b)


def test_resume_without_a_loader():
    full = take(finite(), 9)
    mixture = finite()
    it = iter(mixture)
    first = [clone(next(it)) for _ in range(4)]
    saved = json.loads(json.dumps(mixture.state_dict()))
    it.close()
    assert len(json.dumps(saved)) < 16384  # small: the position and the members' positions
    again = finite()
    again.load_state_dict(saved)
    for a, b in zip(first + take(again, 5), full):
        assert_same(a, b)


def test_resuming_another_configuration_is_refused_naming_it():
    mixture = finite()
    it = iter(mixture)
    next(it)
    saved = json.loads(json.dumps(mixture.state_dict()))
    it.close()
    finite().load_state_dict(saved)  # the same configuration, made anew, resumes
    other = Mixture(three(num_batches=12, continue_episodes=True), weights=[1, 2, 1], seed=8)
    with pytest.raises(ValueError, match="another configuration: seed is 8 here but 7"):
        other.load_state_dict(saved)
    other = Mixture(three(num_batches=12, continue_episodes=True), seed=7)
    with pytest.raises(ValueError, match="another configuration: weights is"):
        other.load_state_dict(saved)
    members = three(num_batches=12, continue_episodes=True)
    members["humanoid"] = member("humanoid", nbatch=2, seed=4, num_batches=12,
                                 continue_episodes=True)
    with pytest.raises(ValueError, match="member 'humanoid': .*seed is 4 here but 3"):
        Mixture(members, weights=[1, 2, 1], seed=7).load_state_dict(saved)
    with pytest.raises(ValueError, match="expected a simloader.Mixture state"):
        finite().load_state_dict(member().state_dict())  # a SimDataset's state


# -- padding ---------------------------------------------------------------------------------

def padded_members():
    return {"pole": member(nbatch=4, seed=1, record=("state", "sensordata", "xpos"),
                           randomize=[dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole")]),
            "humanoid": member("humanoid", nbatch=2, seed=2,
                               record=("state", "sensordata", "xpos"))}


def test_padding_holds_every_members_rows_and_masks_the_real_columns():
    n = 6
    padded = take(Mixture(padded_members(), weights=[1, 2], seed=9, pad=True), n)
    # batch j holds the draws 2j, 2j+1 of the unpadded schedule of the same seed
    unpadded = take(Mixture(padded_members(), weights=[1, 2], seed=9), 2 * n)
    widths = {"state": (56,), "sensordata": (48,), "xpos": (17, 3), "control": (21,),
              "initial_state": (56,)}
    for j, batch in enumerate(padded):
        parts = unpadded[2 * j: 2 * j + 2]
        rows = [p["diverged"].shape[0] for p in parts]
        assert torch.equal(batch["task"], torch.cat([
            torch.full((r,), int(p["task"]), dtype=torch.int64) for p, r in zip(parts, rows)]))
        assert set(batch) == {"state", "sensordata", "xpos", "control", "initial_state",
                              "diverged", "params", "task", "mask/params/body_mass[pole]",
                              *("mask/" + k for k in widths), *simloader.streams.KEYS}
        start = 0
        for part, r in zip(parts, rows):
            sl = slice(start, start + r)
            for key, widest in widths.items():
                value, mask = batch[key][sl], batch["mask/" + key][sl]
                own = part[key]
                assert value.shape[-len(widest):] == widest and mask.shape == (r, *widest)
                real = tuple(slice(0, m) for m in own.shape[own.dim() - len(widest):])
                lead = (slice(None),) * (own.dim() - len(widest))
                assert torch.equal(value[lead + real], own)  # the member's values, unchanged
                rest = value.clone()
                rest[lead + real] = 0
                assert not rest.any(), key  # zeros in the padded columns
                expected_mask = torch.zeros((r, *widest), dtype=torch.bool)
                expected_mask[(slice(None),) + real] = True
                assert torch.equal(mask, expected_mask), key
            assert torch.equal(batch["diverged"][sl], part["diverged"])
            params, pmask = (batch["params"]["body_mass[pole]"][sl],
                             batch["mask/params/body_mass[pole]"][sl])
            if int(part["task"]) == 0:  # only the cart-pole randomizes the pole's mass
                assert torch.equal(params, part["params"]["body_mass[pole]"]) and pmask.all()
            else:
                assert not params.any() and not pmask.any()
            start += r


def test_padding_equal_widths_needs_no_mask():
    mixture = Mixture([member(seed=1), member(nbatch=2, seed=2)], pad=True)
    batch = next(iter(mixture))
    assert not [k for k in batch if k.startswith("mask/")]
    assert batch["state"].shape[0] == batch["task"].shape[0] in (4, 6, 8)


def test_describe_names_each_tasks_columns():
    text = Mixture(padded_members(), weights=[1, 3], pad=True).describe()
    assert "task 0 'pole': share 0.25" in text and "task 1 'humanoid': share 0.75" in text
    assert "qpos: slider, hinge" in text and "right_knee" in text  # the members' own layouts
    assert "state (56,) mask/state: task 0 [:5]; task 1 [:56]" in text
    assert "xpos (17, 3) mask/xpos: task 0 [:3, :3]; task 1 [:17, :3]" in text
    assert ("params/body_mass[pole] (1,) mask/params/body_mass[pole]: task 0 [:1]; task 1 none"
            in text)


@pytest.mark.parametrize("change, message", [
    (dict(nstep=6), r"datasets\['b'\] has nstep 6, datasets\['a'\] 5"),
    (dict(dtype=torch.float32), r"datasets\['b'\] has dtype torch.float32, datasets\['a'\] "
                                r"torch.float64"),
    (dict(record=("state",)), r"datasets\['b'\] has recorded keys"),
    (dict(terminate=simloader.terminate.TimeLimit(3)),
     r"datasets\['b'\] has terminate= rules"),
])
def test_padding_refuses_members_it_cannot_pad(change, message):
    # members that say their dtype (the mixture knows no engine's default)
    with pytest.raises(ValueError, match=r"pad=True: " + message):
        Mixture({"a": member(dtype=torch.float64), "b": member(**{"dtype": torch.float64,
                                                                  **change})}, pad=True)
    Mixture({"a": member(), "b": member(**change)})  # one member per batch: fine


@pytest.mark.parametrize("a, b, said", [
    # one member's engine chooses (float64 on the CPU), the other says float32: the
    # delivered dtype would change from batch to batch with the draws
    (None, torch.float32, r"datasets\['b'\] has dtype torch.float32, datasets\['a'\] None "
                          r"\(backend 'cpu' chooses\)"),
    (torch.float32, torch.float64, r"datasets\['b'\] has dtype torch.float64, datasets\['a'\] "
                                   r"torch.float32"),
], ids=["engine-chosen", "said"])
def test_padding_refuses_members_of_different_dtypes_at_construction(a, b, said):
    with pytest.raises(ValueError, match=r"pad=True: " + said + r"; the float keys of padded "
                                         r"batches \('state', \.\.\.\) need one dtype in every "
                                         r"member: give every member the same dtype="):
        Mixture({"a": member(dtype=a), "b": member(dtype=b)}, pad=True)
    Mixture({"a": member(), "b": member()}, pad=True)  # one engine chooses for both: fine


def test_padding_refuses_a_batch_of_another_dtype_than_its_member_said():
    other = member(dtype=torch.float32)
    # a member that says float64 but delivers float32 (its engine keeps its own configuration)
    other.config = dataclasses.replace(other.config, dtype=torch.float64)
    mix = Mixture({"a": member(dtype=torch.float64), "b": other}, weights=[1, 1], seed=0,
                  pad=True)
    tasks = mix.members(2 * 8)
    mixed = next(j for j in range(8) if len(set(tasks[2 * j: 2 * j + 2])) == 2)
    batches = iter(mix)
    for _ in range(mixed):  # batches of one member: its own dtype throughout
        next(batches)
    with pytest.raises(ValueError, match=r"pad=True: key 'state' came in dtypes \{'.': "
                                         r"torch.float\d\d, '.': torch.float\d\d\} from the "
                                         r"members: padded batches need one dtype per key"):
        next(batches)


def test_padding_refuses_members_on_different_devices():
    other = member()
    # no second device on a CPU machine: the configuration says where the member delivers
    other.config = dataclasses.replace(other.config, device=torch.device("cuda", 1))
    with pytest.raises(ValueError, match=r"pad=True: datasets\['b'\] has device cuda:1, "
                                         r"datasets\['a'\] cpu"):
        Mixture({"a": member(device="cpu"), "b": other}, pad=True)


# -- bad input -----------------------------------------------------------------------------

class MapStyle(torch.utils.data.Dataset):
    def __len__(self):
        return 1

    def __getitem__(self, i):
        return {}


@pytest.mark.parametrize("args, error, message", [
    (lambda: ({}, None), ValueError, r"datasets: expected at least one SimDataset, got an "
                                     r"empty dict"),
    (lambda: ([], None), ValueError, r"datasets: expected at least one"),
    (lambda: (member(), None), TypeError, r"datasets: expected a dict \{name: SimDataset\} or "
                                          r"a sequence of SimDatasets, got SimDataset"),
    (lambda: ({"a": member(), "b": [1]}, None), TypeError,
     r"datasets\['b'\]: expected a simloader.SimDataset, got list"),
    (lambda: ({"a": member(), "b": MapStyle()}, None), TypeError,
     r"datasets\['b'\]: expected a simloader.SimDataset, got MapStyle \(a map-style dataset "
     r"such as simloader.StoredDataset"),
    (lambda: ({"a": Mixture([member()])}, None), TypeError,
     r"datasets\['a'\]: expected a SimDataset, got a Mixture"),
    (lambda: ({1: member()}, None), TypeError, r"datasets: expected names of type str"),
    (lambda: ({"a": member(), "b": member()}, [1, 2, 3]), ValueError,
     r"weights: expected 2 numbers \(one per member: \['a', 'b'\]\), got 3"),
    (lambda: ([member(), member()], [1, -1]), ValueError,
     r"weights\['1'\]: expected a finite number >= 0, got -1"),
    (lambda: ([member(), member()], [1, float("nan")]), ValueError,
     r"weights\['1'\]: expected a finite number >= 0, got nan"),
    (lambda: ([member(), member()], [0, 0.0]), ValueError,
     r"weights: expected at least one weight > 0, got \[0.0, 0.0\]"),
    (lambda: ([member(), member()], ["1", 1]), TypeError,
     r"weights\['0'\]: expected a number >= 0, got str '1'"),
    (lambda: ([member(), member()], 2), TypeError,
     r"weights: expected a sequence of 2 numbers \(one per member\), got int"),
    (lambda: ({"a": member(), "b": member()}, {"a": 1, "c": 1}), ValueError,
     r"weights: expected one weight per member \['a', 'b'\]; missing \['b'\], unknown \['c'\]"),
])
def test_bad_input_is_refused_naming_the_argument(args, error, message):
    datasets, weights = args()
    with pytest.raises(error, match=message):
        Mixture(datasets, weights)


def test_one_member_twice_is_refused():
    ds = member()
    with pytest.raises(ValueError, match=r"datasets\['b'\]: the same SimDataset object as "
                                         r"datasets\['a'\]"):
        Mixture({"a": ds, "b": ds})


def test_bad_seed_and_pad_are_refused():
    with pytest.raises(TypeError, match=r"seed: expected an int >= 0, got float 1.5"):
        Mixture([member()], seed=1.5)
    with pytest.raises(ValueError, match=r"seed: expected an int >= 0, got -1"):
        Mixture([member()], seed=-1)
    with pytest.raises(TypeError, match=r"pad: expected True or False, got str 'yes'"):
        Mixture([member()], pad="yes")


@pytest.mark.parametrize("weights, shares", [
    ([1e308, 1e308], [0.5, 0.5]),  # their sum overflows to inf
    ([1e308, 3e307], [1 / 1.3, 0.3 / 1.3]),
    ([1e-320, 1e-320], [0.5, 0.5]),  # subnormal
    ([1e-320, 3e-320], [0.25, 0.75]),
], ids=["overflowing", "huge", "subnormal", "subnormal-unequal"])
def test_weights_at_the_ends_of_the_floats_normalize(weights, shares):
    mixture = Mixture([member(), member()], weights)
    np.testing.assert_allclose(mixture.weights, shares, rtol=1e-12)
    assert sorted(set(mixture.members(64).tolist())) == [0, 1]  # both members are drawn


def test_weights_as_a_dict_follow_the_names():
    a = Mixture({"a": member(), "b": member()}, {"b": 3, "a": 1})
    assert a.weights.tolist() == [0.25, 0.75]
