"""Errors a new user met: each message says what was wrong and what to do."""

import gc
import re
import time

import pytest
import torch

import simloader
from simloader import randomize as dr


def make(model="cartpole", **kwargs):
    args = dict(backend="cpu", nbatch=2, nstep=3, nthread=1)
    args.update(kwargs)
    return simloader.SimDataset(model, **args)


def test_float32_policy_on_float64_observations_says_what_to_do():
    ds = make(policy=_LinearPolicy(), num_batches=1)
    with pytest.raises(TypeError) as e:
        next(iter(ds))
    msg = str(e.value)
    for part in ("policy", "dtype", "torch.float32", "torch.float64",
                 "SimDataset(..., dtype=torch.float32)", "policy.double()"):
        assert part in msg, (part, msg)
    # the fix works
    ds = make(policy=_LinearPolicy(), num_batches=1, dtype=torch.float32)
    assert next(iter(ds))["state"].dtype == torch.float32


class _LinearPolicy(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.linear = torch.nn.Linear(5, 1)  # cartpole: nstate = 1 + 2 + 2

    def forward(self, obs):
        return self.linear(obs["state"])


def test_policy_reading_an_unrecorded_key_is_told_about_record():
    ds = make(policy=lambda o: o["qpos"][:, :1], num_batches=1)
    with pytest.raises(KeyError) as e:
        next(iter(ds))
    msg = str(e.value)
    assert "'qpos'" in msg and "record=" in msg and "'state'" in msg and "'sensordata'" in msg
    ds = make(policy=lambda o: o["qpos"][:, :1], num_batches=1, record=["qpos"])
    assert "qpos" in next(iter(ds))


def test_batch_from_a_worker_keeps_its_views(tmp_path):
    ds = make(num_batches=1)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=1)
    (batch,) = list(loader)
    assert isinstance(batch, simloader.batch.Batch)
    assert batch.view("qpos").shape == (2, 3, 2)
    # saved, it still loads without simloader's classes
    torch.save(batch, tmp_path / "b.pt")
    loaded = torch.load(tmp_path / "b.pt", weights_only=True)
    assert torch.equal(loaded["state"], batch["state"])


@pytest.mark.parametrize("batch_size", [1, 8])
def test_collation_message_is_true_for_the_batch_size_given(batch_size):
    ds = make(num_batches=20)
    it = iter(torch.utils.data.DataLoader(ds, batch_size=batch_size))
    with pytest.raises(TypeError) as e:
        next(it)
    msg = str(e.value)
    # the dataset's iterator (and its producer thread) ends now, not at a later collection
    del e, it
    gc.collect()
    assert "default batch_size=1 every" not in msg
    assert "batch_size=None" in msg and f"(here {batch_size})" in msg


def test_typo_of_a_keyword_says_did_you_mean():
    with pytest.raises(TypeError, match=re.escape("'n_batches' (did you mean 'num_batches'")):
        make(n_batches=3)


def test_zero_batches_are_refused():
    with pytest.raises(ValueError, match=re.escape(
            "num_batches: expected None or an integer >= 1, got 0")):
        make(num_batches=0)


def test_huge_nbatch_is_refused_before_building_tables():
    start = time.perf_counter()
    with pytest.raises(ValueError, match="nbatch, record: a batch needs"):
        make("humanoid", nbatch=10**7, nstep=100)
    assert time.perf_counter() - start < 2.0


def test_describe_lists_params_keys():
    ds = make(randomize=[dr.scale("body_mass", dr.Uniform(0.5, 1.5), on="pole")])
    text = ds.describe()
    (key,) = next(iter(ds))["params"]
    assert 'batch["params"]' in text and key in text


def test_plain_network_as_policy_is_shown_the_wrapper():
    net = torch.nn.Sequential(torch.nn.Linear(5, 1))  # cartpole: nstate = 1 + 2 + 2
    ds = make(policy=net, num_batches=1, dtype=torch.float32)
    with pytest.raises(TypeError) as e:
        next(iter(ds))
    msg = str(e.value)
    for part in ("policy: it is called with a dict of observation tensors, not a tensor",
                 "keys ['state', 'sensordata']", "'state': (2, 5)", "not Observations",
                 "class Policy(torch.nn.Module):", "def forward(self, obs):",
                 "return self.net(obs['state'])", "SimDataset(..., policy=Policy(net))"):
        assert part in msg, (part, msg)
    assert "dtype" not in msg  # the dtypes agree here: no second fix to make

    # the wrapper the message shows works
    class Policy(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, obs):
            return self.net(obs["state"])

    ds = make(policy=Policy(net), num_batches=1, dtype=torch.float32)
    assert next(iter(ds))["control"].shape == (2, 3, 1)


def test_plain_network_of_another_dtype_is_told_both_fixes():
    ds = make(policy=torch.nn.Sequential(torch.nn.Linear(5, 1)), num_batches=1)
    with pytest.raises(TypeError) as e:
        next(iter(ds))
    msg = str(e.value)
    assert "class Policy(torch.nn.Module):" in msg
    assert "and match the dtypes: policy, dtype:" in msg and "policy.double()" in msg


def test_unbounded_normal_scale_of_a_mass_says_how_to_bound_it():
    with pytest.raises(ValueError) as e:
        make(randomize=[dr.scale("body_mass", dr.Normal(1, 0.1), on="pole")])
    msg = str(e.value)
    assert msg.startswith("randomize: body_mass[pole]: the draw can make body_mass negative"), msg
    assert "give the Normal a lower bound low= >= 0 (and an upper one, high=)" in msg, msg
    example = "dr.scale('body_mass', dr.Normal(1, 0.1, low=0.7, high=1.3), on='pole')"
    assert msg.endswith(f"e.g. {example}"), msg
    # the example it gives is accepted
    ds = make(randomize=[eval(example)], num_batches=1)  # noqa: S307 - the message's own code
    values = next(iter(ds))["params"]["body_mass[pole]"]
    assert ((values >= 0.7 * 0.1 - 1e-12) & (values <= 1.3 * 0.1 + 1e-12)).all()


def _gl_or_skip():
    import os

    from simloader import render
    try:
        render.gl_platform()
    except RuntimeError as e:
        if os.environ.get("SIMLOADER_REQUIRE_GL") == "1":
            raise
        pytest.skip(f"no OpenGL here: {e}")


def test_free_camera_by_its_name_is_the_free_camera():
    _gl_or_skip()
    batches = [next(iter(make(record=("state", simloader.Camera(cam, height=12, width=16)),
                              num_batches=1, seed=3)))
               for cam in ("free", -1)]
    for batch in batches:
        assert [k for k in batch if k.startswith("camera/")] == ["camera/free/rgb"]
    by_name, by_id = (b["camera/free/rgb"] for b in batches)
    assert by_name.shape == (2, 3, 12, 16, 3) and by_name.any()
    assert torch.equal(by_name, by_id)


def test_a_model_camera_named_free_wins_over_the_free_camera():
    import mujoco
    from simloader import records
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><camera name="front" pos="0 -1 0"/><camera name="free" '
        'pos="0 0 1"/><body><freejoint/><geom size=".1"/></body></worldbody></mujoco>')
    (named,) = records.camera_images(model, simloader.Camera("free"))
    (free,) = records.camera_images(model, simloader.Camera(-1))
    assert (named.key, named.camera_id) == ("camera/free/rgb", 1)
    assert (free.key, free.camera_id) == ("camera/free/rgb", -1)
    # elsewhere "free" is the free camera, and an unknown name says so
    cartpole = simloader.load_model("cartpole")
    assert records.camera_images(cartpole, simloader.Camera("free"))[0].camera_id == -1
    with pytest.raises(ValueError, match=re.escape(
            "record: the model has no camera 'fre' (did you mean 'free'?); its cameras: "
            "['front'], or 'free' (or -1) for the free camera")):
        records.camera_images(cartpole, simloader.Camera("fre"))
