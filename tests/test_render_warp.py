"""Cameras on the Warp engine: MuJoCo Warp's renderer inside the step (`backends/warp/cameras.py`).

Without a GPU these run MuJoCo Warp's CPU kernels for real (`SIMLOADER_WARP_ON_CPU=1`, as in
test_warp.py). The reference is MuJoCo C's own ray casting (`mj_multiRay`) through every pixel
centre of the camera at the delivered state: the geom each pixel sees and its planar depth,
independent of any renderer. Warp's ray tracer and MuJoCo's rays differ in float precision only
at silhouette edges, hence the named tolerances.
"""

import math

import mujoco
import numpy as np
import pytest
import torch

pytest.importorskip("warp")

import simloader  # noqa: E402
from simloader import controls  # noqa: E402
from simloader import randomize as dr  # noqa: E402

# pixels whose geom may differ from MuJoCo's rays: those grazing a silhouette, where float32
# and float64 intersections disagree
SEGMENTATION_AGREEMENT = 0.99
# metres, float32 planar depth against float64 rays, where both see the same geom
DEPTH_TOL = 2e-3

# a falling box watched by a fixed camera, a camera riding on the box, one tracking its centre
# of mass and one targeting it; a light tracking it too (the poses a frame needs: mj_camlight)
CAMERAS_XML = """
<mujoco>
  <option timestep="0.01"/>
  <visual><headlight ambient="0.5 0.5 0.5"/></visual>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" rgba="0.3 0.4 0.5 1"/>
    <camera name="fixed" pos="0 -4 1" xyaxes="1 0 0 0 0 1"/>
    <camera name="target" pos="2 -3 2" mode="targetbody" target="box"/>
    <body name="box" pos="0 0 1.2">
      <freejoint/>
      <geom name="box" type="box" size="0.3 0.2 0.1" rgba="0.9 0.3 0.2 1"/>
      <geom name="nose" type="sphere" pos="0.35 0 0" size="0.08" rgba="0.2 0.9 0.2 1"/>
      <camera name="ride" pos="0 -1.5 0.5" xyaxes="1 0 0 0 0.3 1"/>
      <camera name="follow" pos="0 -3 0.5" xyaxes="1 0 0 0 0 1" mode="trackcom"/>
      <light name="spot" pos="0 0 2" mode="trackcom"/>
    </body>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module", autouse=True)
def warp_on_cpu(cache_dir):
    """MuJoCo Warp on the CPU where no GPU is, for this module (as in test_warp.py)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("SIMLOADER_WARP_ON_CPU", "1")
        yield


@pytest.fixture(scope="module")
def cameras_model():
    return mujoco.MjModel.from_xml_string(CAMERAS_XML)


def dataset(model, cache_dir, **kwargs):
    return simloader.SimDataset(model, **{"backend": "warp", **kwargs})


def first(ds):
    return next(iter(torch.utils.data.DataLoader(ds, batch_size=None)))


def rays(model, qpos, camera, height, width):
    """MuJoCo C's view from `camera` at `qpos`: (geom id or -1, planar depth) per pixel."""
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
    half = math.tan(math.radians(model.cam_fovy[cam]) / 2)
    u = (2 * (np.arange(width) + 0.5) / width - 1) * half * width / height
    v = (1 - 2 * (np.arange(height) + 0.5) / height) * half
    local = np.stack(np.broadcast_arrays(u[None, :], v[:, None], -np.ones((1, 1))), -1)
    xmat = data.cam_xmat[cam].reshape(3, 3)
    directions = (local.reshape(-1, 3) / np.linalg.norm(local.reshape(-1, 3), axis=1,
                                                        keepdims=True)) @ xmat.T
    geom = np.zeros(height * width, np.int32)
    dist = np.zeros(height * width)
    mujoco.mj_multiRay(model, data, data.cam_xpos[cam].copy(), directions.ravel().copy(), None,
                       True, -1, geom, dist, None, height * width, mujoco.mjMAXVAL)
    # planar depth: the distance along the ray projected on the optical axis
    planar = dist * (-(directions @ xmat)[:, 2])
    return geom.reshape(height, width), np.where(geom >= 0, planar, 0).reshape(height, width)


def check_view(model, batch, key, qpos, height, width):
    name = key.split("/")[1]
    seg = batch[f"camera/{name}/segmentation"].cpu().numpy()
    depth = batch[f"camera/{name}/depth"].cpu().numpy()
    for i in range(seg.shape[0]):
        for j in range(seg.shape[1]):
            geom, planar = rays(model, qpos[i, j], name, height, width)
            agree = (seg[i, j] == geom).mean()
            assert agree >= SEGMENTATION_AGREEMENT, (name, i, j, agree)
            both = (seg[i, j] == geom) & (geom >= 0)
            np.testing.assert_allclose(depth[i, j][both], planar[both], atol=DEPTH_TOL)


def test_images_show_the_recorded_state_from_every_camera_mode(cameras_model, cache_dir):
    """Fixed, body-mounted, trackcom and targetbody cameras, at the state each frame
    delivers (a falling, tumbling box: poses a step behind would disagree)."""
    nbatch, h, w = 2, 24, 32
    cams = [simloader.Camera(name, height=h, width=w, depth=True, segmentation=True)
            for name in ("fixed", "ride", "follow", "target")]
    x0 = np.zeros((nbatch, mujoco.mj_stateSize(cameras_model, mujoco.mjtState.mjSTATE_FULLPHYSICS)))
    x0[:, 1:8] = [0, 0, 1.2, 1, 0, 0, 0]
    x0[:, 8:14] = [[1.0, 0.5, 3.0, 2.0, -3.0, 1.0], [-1.0, 0.0, 2.0, -2.0, 1.0, 4.0]]
    batch = first(dataset(cameras_model, cache_dir, nbatch=nbatch, nstep=30, record_every=15,
                          initial_state=x0, record=("qpos", *cams)))
    qpos = batch["qpos"].cpu().numpy().astype(np.float64)
    # the box moved and turned between frames: a lagging pose would show
    assert np.abs(qpos[:, 1, :3] - qpos[:, 0, :3]).max() > 0.1
    for cam in cams:
        key = f"camera/{cam.camera}/rgb"
        assert batch[key].shape == (nbatch, 2, h, w, 3) and batch[key].dtype == torch.uint8
        assert batch[f"camera/{cam.camera}/depth"].dtype == torch.float32
        assert batch[f"camera/{cam.camera}/segmentation"].dtype == torch.int32
        check_view(cameras_model, batch, key, qpos, h, w)
    # the box and its nose are seen in colour: red box, green nose
    rgb = batch["camera/fixed/rgb"].cpu().numpy().reshape(-1, 3).astype(int)
    seg = batch["camera/fixed/segmentation"].cpu().numpy().ravel()
    box = rgb[seg == 1]
    assert len(box) and (box[:, 0] > box[:, 1] + 40).mean() > 0.9


def test_cameras_leave_the_physics_unchanged(cameras_model, cache_dir):
    kwargs = dict(nbatch=3, nstep=10, control=None, record_every=5, seed=3,
                  initial_state=simloader.initial.Perturbed(qvel_std=1.0))
    plain = first(dataset(cameras_model, cache_dir, record=("qpos", "xpos"), **kwargs))
    seen = first(dataset(cameras_model, cache_dir, record=(
        "qpos", "xpos", simloader.Camera("ride", height=8, width=8)), **kwargs))
    for key in ("qpos", "xpos", "initial_state"):
        assert torch.equal(plain[key], seen[key]), key


def test_cartpole_rgb_uint8_and_float64_keeps_depth_float32(cache_dir):
    batch = first(dataset("cartpole", cache_dir, nbatch=2, nstep=4, record_every=2,
                          dtype=torch.float64, control=controls.Uniform(),
                          record=("qpos", simloader.Camera("front", depth=True))))
    assert batch["qpos"].dtype == torch.float64
    assert batch["camera/front/rgb"].shape == (2, 2, 64, 64, 3)
    assert batch["camera/front/depth"].dtype == torch.float32
    rgb = batch["camera/front/rgb"].cpu().numpy()
    assert rgb.max() > 100 and len(np.unique(rgb)) > 10  # lit, not blank


def test_randomized_colours_show_per_trajectory(cache_dir):
    spec = [dr.set("geom_rgba", dr.Uniform(0.0, 1.0), on="cart", index=[0, 1, 2])]
    batch = first(dataset("cartpole", cache_dir, nbatch=4, nstep=1, randomize=spec,
                          record=(simloader.Camera("front", segmentation=True),)))
    rgba = batch["params"]["geom_rgba[cart]"].cpu().numpy().reshape(4, 3)
    seg = batch["camera/front/segmentation"].cpu().numpy()[:, 0]
    rgb = batch["camera/front/rgb"].cpu().numpy()[:, 0].astype(float)
    cart = mujoco.mj_name2id(simloader.load_model("cartpole"), mujoco.mjtObj.mjOBJ_GEOM, "cart")
    means = np.stack([rgb[i][seg[i] == cart].mean(axis=0) for i in range(4)])
    # shading scales each channel alike: the seen colour follows the drawn one
    for channel in range(3):
        assert np.corrcoef(means[:, channel], rgba[:, channel])[0, 1] > 0.9, channel


def test_refusals(cache_dir):
    with pytest.raises(ValueError, match="free camera"):
        dataset("cartpole", cache_dir, nbatch=2, nstep=2, record=(simloader.Camera(-1),))
    with pytest.raises(ValueError, match="one size"):
        dataset("cartpole", cache_dir, nbatch=2, nstep=2, record=(
            simloader.Camera("front"), simloader.Camera("front", 32, 32, rgb=False, depth=True)))


def test_a_batch_of_frames_too_large_for_memory_is_refused(cache_dir):
    """65536 trajectories x 100 frames x 64x64 RGB is 80 GB: refused with the numbers."""
    with pytest.raises(ValueError, match=r"nbatch, record: a batch needs .*GiB"):
        dataset("cartpole", cache_dir, nbatch=65536, nstep=100,
                record=(simloader.Camera("front"),))


@pytest.mark.parametrize("height, width", [(8, 6), (5, 3)])  # whole words, and not
def test_rgb_unpacking_gives_each_pixels_channels_in_place(height, width):
    """Warp's packed pixels (red in bits 16-23, blue in 0-7) as uint8 RGB in the asked frame
    only, by the kernel of whole words and by the one of single pixels."""
    import warp as wp

    from simloader.backends.warp import cameras, runtime
    runtime.warp()
    n, nframes, npixel = 3, 4, height * width
    gen = torch.Generator().manual_seed(0)
    packed = torch.randint(0, 2**24, (n, npixel), generator=gen, dtype=torch.int32)
    stored = torch.zeros((n, nframes, height, width, 3), dtype=torch.uint8)
    with wp.ScopedDevice("cpu"):
        cameras._unpack_rgb(wp, wp.from_torch(packed, dtype=wp.uint32),
                            torch.tensor([2]), stored)
    want = torch.stack([(packed >> s) & 255 for s in (16, 8, 0)], dim=-1).to(torch.uint8)
    assert torch.equal(stored[:, 2], want.reshape(n, height, width, 3))
    assert not stored[:, [0, 1, 3]].any()
