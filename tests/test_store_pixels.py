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
    with pytest.raises(ValueError, match=r"model: not the model the store .* was simulated"):
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
