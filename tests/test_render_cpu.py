"""Cameras on the rollout backend (`simloader/render.py`): every image equals a plain
`mujoco.Renderer` of the same model and state (after `mj_forward`) bit for bit.

These render for real with OpenGL (EGL: Mesa's software rasterizer on a CPU-only machine).
Without a working GL they skip, unless SIMLOADER_REQUIRE_GL=1 (CI sets it) makes them fail.
"""

import os

import mujoco
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import simloader
from simloader import controls
from simloader import randomize as dr
from simloader import render as cpu_render


@pytest.fixture(scope="module", autouse=True)
def gl():
    try:
        return cpu_render.gl_platform()
    except RuntimeError as e:
        if os.environ.get("SIMLOADER_REQUIRE_GL") == "1":
            raise
        pytest.skip(f"no OpenGL here: {e}")


def reference(model, state, camera, height, width, kind, renderers=None):
    """A plain mujoco.Renderer's image of `model` at FULLPHYSICS `state`. `renderers`: a dict
    that keeps one renderer per (model, size) for the next call (creating a GL context per
    image costs as much as the image); the caller closes them."""
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    mujoco.mj_forward(model, data)
    key = (id(model), height, width)
    renderer = None if renderers is None else renderers.get(key)
    if renderer is None:
        with cpu_render._swapped_gl(cpu_render.gl_platform()[0]):
            renderer = mujoco.Renderer(model, height, width)
        if renderers is not None:
            renderers[key] = renderer
    try:
        renderer.update_scene(data, camera)
        if kind == "depth":
            renderer.enable_depth_rendering()
        if kind == "segmentation":
            renderer.enable_segmentation_rendering()
            seg = renderer.render()
            return np.where(seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, seg[..., 0], -1)
        return renderer.render()
    finally:
        if renderers is None:
            renderer.close()
        else:  # back to plain RGB for the next image
            renderer.disable_depth_rendering()
            renderer.disable_segmentation_rendering()


def check_images(batch, models, cams, frames=None):
    states = batch["state"].numpy()
    renderers = {}
    try:
        for cam in cams:
            name = cam.camera if isinstance(cam.camera, str) else "free"
            for kind in cam.kinds:
                images = batch[f"camera/{name}/{kind}"].numpy()
                for i in range(images.shape[0]):
                    for j in frames or range(images.shape[1]):
                        ref = reference(models[i], states[i, j], cam.camera, cam.height,
                                        cam.width, kind, renderers)
                        assert np.array_equal(images[i, j], ref), (name, kind, i, j)
    finally:
        for renderer in renderers.values():
            renderer.close()


CARTPOLE_CAMS = (simloader.Camera("front", depth=True, segmentation=True),
                 simloader.Camera(-1, height=24, width=40))


def test_images_equal_a_plain_renderer():
    model = simloader.load_model("cartpole")
    ds = simloader.SimDataset(model, backend="cpu", nbatch=3, nstep=9, record_every=3,
                              record=("state", *CARTPOLE_CAMS), control=controls.Uniform(),
                              initial_state=simloader.initial.Perturbed(qpos_std=0.5),
                              nthread=2)
    batch = next(iter(ds))
    assert batch["camera/front/rgb"].shape == (3, 3, 64, 64, 3)
    assert batch["camera/front/rgb"].dtype == torch.uint8
    assert batch["camera/front/depth"].dtype == torch.float32
    assert batch["camera/front/segmentation"].dtype == torch.int32
    assert batch["camera/free/rgb"].shape == (3, 3, 24, 40, 3)
    check_images(batch, [model] * 3, CARTPOLE_CAMS)
    # the cart and pole are seen, and move between frames
    seg = batch["camera/front/segmentation"].numpy()
    assert {model.geom("cart").id, model.geom("pole").id} <= set(np.unique(seg))
    assert not np.array_equal(batch["camera/front/rgb"][:, 0], batch["camera/front/rgb"][:, 2])


def test_humanoid_tracking_cameras_continuing():
    model = simloader.load_model("humanoid")
    cams = (simloader.Camera("back", 32, 32), simloader.Camera("egocentric", 24, 24,
                                                               segmentation=True))
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=10, record_every=5,
                              record=("state", *cams), control=controls.Uniform(),
                              continue_episodes=True, nthread=2)
    it = iter(ds)
    next(it)
    check_images(next(it), [model] * 2, cams)


def test_randomized_colours_and_model_lists_render_per_trajectory():
    model = simloader.load_model("cartpole")
    cam = (simloader.Camera("front", 32, 32),)
    spec = [dr.set("geom_rgba", dr.Uniform(0.0, 1.0), on="cart", index=[0, 1, 2])]
    batch = next(iter(simloader.SimDataset(model, backend="cpu", nbatch=3, nstep=2,
                                           randomize=spec, record=("state", *cam), nthread=2)))
    rgba = batch["params"]["geom_rgba[cart]"].numpy()
    models = []
    for i in range(3):
        m = simloader.load_model("cartpole")
        m.geom_rgba[m.geom("cart").id, :3] = rgba[i]
        models.append(m)
    check_images(batch, models, cam)
    assert not np.array_equal(batch["camera/front/rgb"][0], batch["camera/front/rgb"][1])
    # a model list: trajectory i on models[i]
    batch = next(iter(simloader.SimDataset(model, backend="cpu", nbatch=3, nstep=2,
                                           randomize=models, record=("state", *cam))))
    check_images(batch, models, cam)


def test_in_spawned_workers():
    model = simloader.load_model("cartpole")
    cam = (simloader.Camera("front", 16, 16),)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=2, num_batches=2,
                              record=("state", *cam), control=controls.Uniform(), nthread=1)
    batches = list(DataLoader(ds, batch_size=None, num_workers=2,
                              multiprocessing_context="spawn"))
    assert len(batches) == 2
    for batch in batches:
        check_images(batch, [model] * 2, cam)


def test_refusals():
    model = simloader.load_model("cartpole")
    with pytest.raises(ValueError, match=r"offscreen framebuffer 480x640.*offwidth=\"1000\""):
        simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=2,
                             record=(simloader.Camera("front", height=100, width=1000),))
    with pytest.raises(ValueError, match="policy, record"):
        simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=2,
                             record=("qpos", simloader.Camera("front")),
                             policy=lambda obs: torch.zeros(2, 1))
    # 1e6 trajectories x 100 frames of 64x64 RGB: 1.1 TiB, refused with the numbers
    with pytest.raises(ValueError, match=r"nbatch, record: a batch needs .* GiB"):
        simloader.SimDataset(model, backend="cpu", nbatch=10**6, nstep=100,
                             record=(simloader.Camera("front"),))


# A dataset with a camera made in the main process (which probes GL there), iterated by a
# DataLoader: argv[1] is "0" (num_workers=0) or a start method for num_workers=1; argv[2]
# "render-first" renders a batch in the main process before the workers start. Prints one
# line per batch: the images' checksum.
LOADER_SCRIPT = """
import hashlib, sys
import simloader
from torch.utils.data import DataLoader

def main(how, first):
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=2, nstep=4, seed=7,
                              record=("state", simloader.Camera("front", height=16, width=16)),
                              num_batches=2, nthread=1)
    if first == "render-first":
        next(iter(ds))
    kw = (dict(num_workers=0) if how == "0"
          else dict(num_workers=1, multiprocessing_context=how))
    try:
        for batch in DataLoader(ds, batch_size=None, **kw):
            rgb = batch["camera/front/rgb"].numpy()
            assert rgb.shape == (2, 4, 16, 16, 3) and rgb.any()
            print(hashlib.sha256(rgb.tobytes()).hexdigest(), flush=True)
    except RuntimeError as e:
        print("refused:", str(e).replace(chr(10), " "))

if __name__ == "__main__":
    main(*sys.argv[1:])
"""


def test_workers_and_start_methods(fresh_python):
    """num_workers=0, and one worker forked (Linux's default) or spawned, yield the same
    images: the GL probe leaves nothing in the parent that a fork breaks (it hung before)."""
    runs = [(("0", "-"), None), (("fork", "-"), None), (("spawn", "-"), None)]
    outs = fresh_python(LOADER_SCRIPT, runs, timeout=120)
    expected = outs[0].split()
    assert len(expected) == 2 and not outs[0].startswith("refused")
    for (args, _), out in zip(runs[1:], outs[1:]):
        assert out.split() == expected, (args, out)


def test_fork_after_rendering_is_refused_not_hung(fresh_python):
    """Rendering in the main process, then forking workers, is refused naming the fix (the
    driver's state would come along without its threads and hang)."""
    fork, = fresh_python(LOADER_SCRIPT, [(("fork", "render-first"), None)], timeout=120)
    assert fork.startswith("refused:"), fork
    assert "multiprocessing_context" in fork and "spawn" in fork and "num_workers=0" in fork


def test_shadows_and_multisampling_can_be_switched_off_and_equal_a_plain_renderer_so_made():
    """`Camera(shadows=False, multisample=False)` on a MuJoCo Menagerie scene (the Go1 of
    tests/robots: 4096-pixel shadow maps, multisampling): every image equals a plain
    `mujoco.Renderer` made from the model without offscreen samples, its scene's shadow flag
    off; the default still draws both."""
    import copy
    import pathlib
    path = pathlib.Path(__file__).parent / "robots" / "unitree_go1" / "scene.xml"
    model = mujoco.MjModel.from_xml_path(str(path))
    plain_cam = simloader.Camera(-1, height=32, width=32, shadows=False, multisample=False)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=2, num_batches=1,
                              record=("state", plain_cam))
    batch = next(iter(ds))
    plain = copy.copy(model)
    plain.vis.quality.offsamples = 0
    data = mujoco.MjData(model)
    with cpu_render._swapped_gl(cpu_render.gl_platform()[0]):
        renderer, default = mujoco.Renderer(plain, 32, 32), mujoco.Renderer(model, 32, 32)
    with renderer, default:
        for i in range(2):
            for t in range(2):
                mujoco.mj_setState(model, data, batch["state"][i, t].numpy(),
                                   mujoco.mjtState.mjSTATE_FULLPHYSICS)
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, -1)
                renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
                np.testing.assert_array_equal(batch["camera/free/rgb"][i, t].numpy(),
                                              renderer.render())
        default.update_scene(data, -1)  # the default draws both: other pixels
        assert not np.array_equal(batch["camera/free/rgb"][1, 1].numpy(), default.render())
    with pytest.raises(TypeError, match="Camera: shadows must be a bool"):
        simloader.Camera(-1, shadows="no")
