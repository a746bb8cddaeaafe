"""`simloader.video`: the MP4 decoded gives the frames the CPU engine's camera renders."""

import numpy as np
import pytest
import torch

import simloader

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

H, W = 48, 64


def decode(path):
    """(nframes, height, width, 3) uint8 of a video file."""
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    width, height = meta["size"]
    frames = [np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader]
    return np.stack(frames), meta


@pytest.fixture(scope="module")
def streamed():
    """A cart-pole batch streamed with the free camera on the CPU engine, and its dataset."""
    ds = simloader.SimDataset("cartpole", nbatch=3, nstep=12, backend="cpu", seed=3,
                              control=simloader.controls.Uniform(),
                              record=("state", simloader.Camera(-1, height=H, width=W)))
    return ds, next(iter(ds))


def without_camera(batch):
    return {k: v for k, v in batch.items() if not k.startswith("camera/")}


def test_a_lossless_mp4_of_states_decodes_to_the_engines_camera_pixels(streamed, tmp_path):
    ds, batch = streamed
    path = simloader.video(without_camera(batch), tmp_path / "a.mp4", model=ds, rows=[2, 0],
                           size=(H, W), fps=10, lossless=True, progress=False)
    frames, meta = decode(path)
    images = batch["camera/free/rgb"].numpy()
    assert frames.shape == (12, H, W * 2, 3)
    assert meta["fps"] == 10
    # row 2 on the left, row 0 on the right, every frame bit for bit
    np.testing.assert_array_equal(frames[:, :, :W], images[2])
    np.testing.assert_array_equal(frames[:, :, W:], images[0])
    assert images[2].std() > 0 and not np.array_equal(images[2], images[0])


def test_a_recorded_camera_is_used_as_recorded(streamed, tmp_path):
    _, batch = streamed
    path = simloader.video(batch, tmp_path / "rec.mp4", rows=1, fps=5, lossless=True,
                           progress=False)
    frames, _ = decode(path)
    np.testing.assert_array_equal(frames, batch["camera/free/rgb"][1].numpy())


def test_the_default_mp4_plays_everywhere_and_stays_close(streamed, tmp_path):
    ds, batch = streamed
    path = simloader.video(without_camera(batch), tmp_path / "b.mp4", model=ds, rows=[0],
                           size=(H, W), fps=10, progress=False)
    frames, _ = decode(path)
    assert frames.shape == (12, H, W, 3)
    error = np.abs(frames.astype(int) - batch["camera/free/rgb"][0].numpy().astype(int))
    assert error.mean() < 6, error.mean()


def test_real_time_by_default_from_the_states_time(tmp_path):
    # cart-pole's timestep is 0.01 s: 100 frames a second, shown every 2nd at 50 fps
    ds = simloader.SimDataset("cartpole", nbatch=1, nstep=10, backend="cpu", seed=0)
    path = simloader.video(ds, tmp_path / "c.mp4", size=(32, 32), progress=False)
    frames, meta = decode(path)
    step = ds.config.model.opt.timestep
    assert len(frames) == 5 and meta["fps"] == pytest.approx(1 / (2 * step))


def test_a_store_renders_with_the_dataset_that_wrote_it(streamed, tmp_path):
    ds, batch = streamed
    plain = simloader.SimDataset("cartpole", nbatch=3, nstep=12, backend="cpu", seed=3,
                                 control=simloader.controls.Uniform(), num_batches=1)
    simloader.write(plain, tmp_path / "store", batches=1)
    path = simloader.video(tmp_path / "store", tmp_path / "s.mp4", model=plain, rows=[1],
                           size=(H, W), fps=10, lossless=True, progress=False)
    frames, _ = decode(path)
    np.testing.assert_array_equal(frames, batch["camera/free/rgb"][1].numpy())
    # without model=: the store kept the model it was simulated with
    path = simloader.video(tmp_path / "store", tmp_path / "k.mp4", rows=[1], size=(H, W),
                           fps=10, lossless=True, progress=False)
    np.testing.assert_array_equal(decode(path)[0], frames)


def test_a_gif(streamed, tmp_path):
    ds, batch = streamed
    path = simloader.video(without_camera(batch), tmp_path / "d.gif", model=ds, rows=[0, 1],
                           size=(H, W), fps=10, progress=False)
    import imageio.v3 as iio
    frames = iio.imread(path, index=None)
    assert frames.shape[:3] == (12, H, 2 * W)


@pytest.mark.parametrize("kwargs, message", [
    (dict(path="a.avi"), "path: expected a file ending in .mp4 or .gif, got"),
    (dict(rows=[0, 7]), "rows: [7] out of range for 3 trajectories"),
    (dict(rows=[]), "rows: expected an int or a non-empty sequence of ints"),
    (dict(size=(0, 10)), "size: expected (height, width) in pixels, got (0, 10)"),
    (dict(fps=0), "fps: expected a number in (0, 1000], got 0"),
    (dict(path="a.gif", lossless=True), "lossless: only an MP4 can be lossless"),
    (dict(model=None), "model: rendering states needs the model that made them"),
    (dict(camera="nope"), "the model has no camera 'nope'"),
])
def test_bad_arguments_are_named(streamed, tmp_path, kwargs, message):
    ds, batch = streamed
    kwargs = {"model": ds, "path": "a.mp4", **kwargs}
    path = tmp_path / kwargs.pop("path")
    with pytest.raises(ValueError) as e:
        simloader.video(without_camera(batch), path, progress=False, **kwargs)
    assert message in str(e.value)
    assert not path.exists()


def test_a_source_without_states_or_camera_says_what_to_record(tmp_path):
    batch = {"sensordata": torch.zeros(2, 3, 4)}
    with pytest.raises(ValueError, match="expected a batch of simloader"):
        simloader.video(batch, tmp_path / "e.mp4", model="cartpole", progress=False)


def test_the_command_line_for_a_model_and_a_store(tmp_path):
    from simloader import cli
    out = tmp_path / "m.mp4"
    cli.main(["video", "cartpole", str(out), "--rows", "0", "2", "--nstep", "20",
              "--size", "32", "48", "--fps", "10"])
    frames, _ = decode(out)
    assert frames.shape == (20, 32, 96, 3)
    ds = simloader.SimDataset("cartpole", nbatch=2, nstep=10, backend="cpu", seed=0,
                              num_batches=1)
    simloader.write(ds, tmp_path / "store", batches=1)
    with pytest.raises(SystemExit):  # a store needs its model
        cli.main(["video", str(tmp_path / "store"), str(tmp_path / "s.mp4")])
    cli.main(["video", str(tmp_path / "store"), str(tmp_path / "s.mp4"), "--model", "cartpole",
              "--rows", "1", "--fps", "10", "--size", "32", "32", "--lossless"])
    frames, _ = decode(tmp_path / "s.mp4")
    assert frames.shape == (10, 32, 32, 3)


def test_a_fresh_start_is_framed_and_nothing_else_changes(tmp_path):
    from simloader.terminate import Outside
    ds = simloader.SimDataset("cartpole", nbatch=2, nstep=30, backend="cpu", seed=1,
                              control=simloader.controls.Uniform(),
                              terminate=Outside("hinge", -0.03, 0.03),
                              record=("state", simloader.Camera(-1, height=H, width=W)))
    batch = next(iter(ds))
    first = batch["first"].numpy()
    assert first.any() and not first.all()
    path = simloader.video(batch, tmp_path / "f.mp4", rows=[0, 1], fps=10, lossless=True,
                           progress=False)
    frames, _ = decode(path)
    images = batch["camera/free/rgb"].numpy()
    border = max(1, min(H, W) // 24)
    for t in range(len(frames)):
        for i in range(2):
            tile = frames[t, :H, i * W:(i + 1) * W]
            if first[i, t]:
                assert (tile[:border] == simloader.videos.MARK).all()
                np.testing.assert_array_equal(tile[border:-border, border:-border],
                                              images[i, t, border:-border, border:-border])
            else:
                np.testing.assert_array_equal(tile, images[i, t])
    assert images.flags.writeable and not (images[:, :, :border] == simloader.videos.MARK).all()
