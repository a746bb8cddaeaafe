"""Pixels from stored states (CPU renderer): a store of states renders its cameras on read,
bit for bit as the CPU engine's streamed camera, for items, transitions and DataLoader
workers; what it cannot render is refused at construction, naming what to do."""

import os
import shutil

import numpy as np
import pytest
import torch

import simloader

pytest.importorskip("zarr")

CAMERA = simloader.Camera("front", height=32, width=40)


def cartpole(record, **kwargs):
    base = dict(backend="cpu", nbatch=6, nstep=12, nthread=2, seed=4,
                control=simloader.controls.Uniform(), record=record,
                # a colour per trajectory: each frame must be drawn with its own model
                randomize=[simloader.randomize.set("geom_rgba", simloader.randomize.Uniform(
                    0.2, 1.0), on=["pole"])])
    base.update(kwargs)
    return simloader.SimDataset("cartpole", **base)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A store of states only, and the same stream with the camera."""
    folder = tmp_path_factory.mktemp("pixels")
    path = simloader.write(cartpole(("state",)), folder / "s.zarr", batches=2, progress=False)
    streamed = [b for _, b in zip(range(2), cartpole(("state", CAMERA)))]
    return path, torch.cat([b["camera/front/rgb"] for b in streamed])


def test_items_render_on_read_the_pixels_the_stream_delivered(written):
    path, want = written
    stored = simloader.StoredDataset(path, cameras=CAMERA)
    assert len(stored) == 12
    for i in range(len(stored)):
        item = stored[i]
        assert item["camera/front/rgb"].dtype == torch.uint8
        assert torch.equal(item["camera/front/rgb"], want[i]), f"trajectory {i}"
    # the randomized colour shows: the trajectories differ
    assert not torch.equal(want[0, 0], want[1, 0])


def test_transitions_carry_both_frames_rendered(written):
    path, want = written
    transitions = simloader.StoredDataset(path, cameras=CAMERA).transitions()
    ks = np.arange(0, len(transitions), 5)
    batch = transitions.gather(ks[::-1].copy())  # out of order too
    trajectories, frames = transitions.locate(ks[::-1].copy())
    for k, (t, f) in enumerate(zip(trajectories, frames)):
        assert torch.equal(batch["next/camera/front/rgb"][k], want[t, f])
        if f > 0:
            assert torch.equal(batch["camera/front/rgb"][k], want[t, f - 1])
    assert batch["camera/front/rgb"].shape == (len(ks), 32, 40, 3)


def test_transitions_of_another_key_read_the_states_for_their_frames(written, tmp_path):
    # the transitions pair qpos, not the state: the cameras read the states themselves
    _, want = written
    path = simloader.write(cartpole(("state", "qpos")), tmp_path / "q.zarr", batches=2,
                           progress=False)
    transitions = simloader.StoredDataset(path, cameras=CAMERA).transitions(state="qpos")
    ks = np.arange(0, len(transitions), 3)[::-1].copy()
    batch = transitions.gather(ks)
    assert "state" not in batch and "qpos" in batch
    for k, (t, f) in enumerate(zip(*transitions.locate(ks))):
        assert torch.equal(batch["next/camera/front/rgb"][k], want[t, f])
        if f > 0:
            assert torch.equal(batch["camera/front/rgb"][k], want[t, f - 1])


def test_dataloader_workers_render_their_items(written):
    path, want = written
    stored = simloader.StoredDataset(path, cameras=CAMERA, keys=["state"])
    loader = torch.utils.data.DataLoader(stored, batch_size=4, num_workers=2,
                                         multiprocessing_context="spawn")
    got = torch.cat([b["camera/front/rgb"] for b in loader])
    assert torch.equal(got, want)


def test_what_cannot_be_rendered_is_refused_naming_it(written, tmp_path):
    path, _ = written
    with pytest.raises(ValueError, match=r"cameras: the model has no camera 'side'.*its "
                                         r"cameras: \[.front.\]"):
        simloader.StoredDataset(path, cameras=simloader.Camera("side"))
    no_state = simloader.write(cartpole(("qpos",)), tmp_path / "q.zarr", batches=1,
                               progress=False)
    with pytest.raises(ValueError, match=r"has no 'state'.*record=\(\"state\",\)"):
        simloader.StoredDataset(no_state, cameras=CAMERA)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"backend='warp' (cannot render stored states "
                                             r"here|renders stored states on a CUDA GPU)"):
            simloader.StoredDataset(path, cameras=CAMERA, backend="warp")
    with pytest.raises(ValueError, match=r"backend: expected 'auto' or one of"):
        simloader.StoredDataset(path, cameras=CAMERA, backend="opengl")
    with pytest.raises(TypeError, match=r"cameras: expected a simloader.Camera"):
        simloader.StoredDataset(path, cameras="fixed")
    with pytest.raises(ValueError,
                       match=r"model: not the model\(s\) the store .* was simulated"):
        simloader.StoredDataset(path, cameras=CAMERA, model="humanoid")


def test_a_store_without_its_model_files_renders_with_the_model_given(written, tmp_path):
    path, want = written
    copy = str(tmp_path / "c.zarr")
    shutil.copytree(path, copy)
    shutil.rmtree(os.path.join(copy, "provenance", "models"))
    with pytest.raises(ValueError, match=r"model .* is missing .*pass model="):
        simloader.StoredDataset(copy, cameras=CAMERA)
    stored = simloader.StoredDataset(copy, cameras=CAMERA, model="cartpole")
    assert torch.equal(stored[7]["camera/front/rgb"], want[7])


def longer_pole(spec, rng):
    length = rng.uniform(0.5, 1.5)
    spec.geom("pole").fromto = [0, 0, 0, 0, 0, length]
    spec.site("tip").pos = [0, 0, length]
    return spec


@pytest.mark.parametrize("pool", ["variants", "models"])
def test_structural_variants_and_model_lists_render_each_trajectorys_model(pool, tmp_path):
    """A store of states of variants (or of a model list) renders every trajectory with its
    own model, as streaming did; an older store without kept models needs them all given."""
    if pool == "variants":
        randomize = simloader.randomize.Variants(longer_pole, count=3)
    else:
        import mujoco
        base = simloader.load_model("cartpole")
        randomize = []
        for k in range(6):
            m = mujoco.MjModel.from_xml_path(str(simloader.builtin_path("cartpole")))
            m.geom_rgba[-1] = [0.2 + 0.1 * k, 0.3, 0.9 - 0.1 * k, 1.0]
            randomize.append(m)
        assert base.ngeom == randomize[0].ngeom
    path = simloader.write(cartpole(("state",), randomize=randomize), tmp_path / "v.zarr",
                           batches=1, progress=False)
    want = next(iter(cartpole(("state", CAMERA), randomize=randomize)))["camera/front/rgb"]
    stored = simloader.StoredDataset(path, cameras=CAMERA)
    for i in range(6):
        assert torch.equal(stored[i]["camera/front/rgb"], want[i]), i
    assert len({want[i, 0].numpy().tobytes() for i in range(6)}) > 1  # the models differ


def test_an_older_store_of_a_model_list_renders_with_the_list_given(tmp_path):
    import json
    import mujoco
    models = []
    for k in range(6):
        m = mujoco.MjModel.from_xml_path(str(simloader.builtin_path("cartpole")))
        m.geom_rgba[-1] = [0.2 + 0.1 * k, 0.3, 0.9 - 0.1 * k, 1.0]
        models.append(m)
    path = simloader.write(cartpole(("state",), randomize=models), tmp_path / "o.zarr",
                           batches=1, progress=False)
    # as written before stores kept their models
    shutil.rmtree(os.path.join(path, "provenance", "models"))
    root = os.path.join(path, "zarr.json")
    meta = json.load(open(root))
    del meta["attributes"]["simloader"]["models"]
    json.dump(meta, open(root, "w"))
    want = next(iter(cartpole(("state", CAMERA), randomize=models)))["camera/front/rgb"]
    with pytest.raises(ValueError, match=r"written before simloader kept the model"):
        simloader.StoredDataset(path, cameras=CAMERA)
    with pytest.raises(ValueError, match=r"model: not the model\(s\)"):
        simloader.StoredDataset(path, cameras=CAMERA, model=models[0])
    stored = simloader.StoredDataset(path, cameras=CAMERA, model=models)
    assert all(torch.equal(stored[i]["camera/front/rgb"], want[i]) for i in range(6))


def test_a_linked_model_file_is_not_read(written, tmp_path):
    path, _ = written
    copy = str(tmp_path / "m.zarr")
    shutil.copytree(path, copy)
    model = os.path.join(copy, "provenance", "models", "0.mjb.zlib")
    os.unlink(model)
    os.symlink(os.path.join(path, "provenance", "models", "0.mjb.zlib"), model)
    # refused when the store is opened (a store never follows a link), before rendering
    with pytest.raises(ValueError, match=r"the store holds links.*0\.mjb\.zlib"):
        simloader.StoredDataset(copy, cameras=CAMERA)
