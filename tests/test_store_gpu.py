"""simloader.write on the GPU engines (marker gpu): Warp batches with a camera into a store,
read back and regenerated from their provenance within the engine's tolerance.

Needs no zarr (the store is simloader's own reading and writing); numcodecs for the images.
"""

import pytest
import torch

import simloader

pytestmark = [pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]

# a regenerated Warp trajectory against the stored one (humanoid, 20 float32 steps with
# contacts): MuJoCo Warp's contact and constraint kernels sum with atomics, in an order that
# may differ between runs
REGENERATE_TOL = 1e-3


def humanoid(impl, camera=False):
    record = ("state", "qvel") + ((simloader.Camera("back", height=32, width=32),) if camera
                                  else ())
    return simloader.SimDataset("humanoid", backend=impl, nbatch=64, nstep=20,
                                control=simloader.controls.Uniform(), record=record, seed=3)


@pytest.mark.parametrize("impl", ["warp", "mjx"])
def test_gpu_store_reads_back_and_regenerates_within_tolerance(impl, tmp_path):
    pytest.importorskip("numcodecs")
    if impl == "warp":
        pytest.importorskip("warp")
    ds = humanoid(impl, camera=impl == "warp")
    path = simloader.write(ds, tmp_path / "g.zarr", batches=2, progress=False)
    stored = simloader.StoredDataset(path)
    assert len(stored) == 128
    item = stored[70]
    assert item["state"].dtype == torch.float32 and item["state"].device.type == "cpu"
    again = stored.regenerate(humanoid(impl, camera=impl == "warp"), 70)
    difference = (again["state"] - item["state"]).abs().max().item()
    print(f"{impl}: regenerated state differs by at most {difference:.2e}")
    assert difference <= REGENERATE_TOL
    assert torch.equal(again["initial_state"], item["initial_state"])
    if impl == "warp":
        rgb = item["camera/back/rgb"]
        assert rgb.dtype == torch.uint8 and rgb.shape == (20, 32, 32, 3)
        assert (again["camera/back/rgb"] != rgb).float().mean().item() < 0.01
