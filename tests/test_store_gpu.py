"""simloader.write on the GPU engines (marker gpu): Warp batches with a camera into a store,
read back and regenerated from their provenance within the engine's tolerance.

Needs no zarr (the store is simloader's own reading and writing); numcodecs for the images.
"""

import numpy as np
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


@pytest.mark.parametrize("impl", ["warp", "mjx"])
def test_a_pipelined_gpu_write_stores_exactly_the_batches_it_was_handed(impl, tmp_path,
                                                                         monkeypatch):
    """The copies to pinned host memory are asynchronous, overlapped with the next batches'
    simulation: each stored slot must equal, bit for bit, the batch as it was handed over
    (a copy that raced with the engine's next batch would differ), and the pinned buffers
    are recycled (no more sets than slots in flight)."""
    if impl == "warp":
        pytest.importorskip("warp")
    from simloader.store import pipeline
    handed, made = {}, []
    real_submit, real_take = pipeline.SlotPipeline.submit, pipeline._HostCopies._take

    def submit(self, slot, batch, where):
        handed[slot] = {k: v.detach().cpu().clone() for k, v in batch.items()
                        if isinstance(v, torch.Tensor)}
        return real_submit(self, slot, batch, where)

    def take(self, shape, dtype):
        before = sum(len(v) for v in self.free.values())
        out = real_take(self, shape, dtype)
        if sum(len(v) for v in self.free.values()) == before:
            made.append((shape, dtype))  # none was free: a new pinned buffer
        return out

    monkeypatch.setattr(pipeline.SlotPipeline, "submit", submit)
    monkeypatch.setattr(pipeline._HostCopies, "_take", take)
    batches = 6
    path = simloader.write(humanoid(impl), tmp_path / "p.zarr", batches=batches,
                           progress=False)
    stored = simloader.StoredDataset(path)
    assert sorted(handed) == list(range(batches))
    for slot, batch in handed.items():
        for key in ("state", "qvel", "control"):
            rows = torch.stack([stored[slot * 64 + r][key] for r in range(64)])
            assert torch.equal(rows, batch[key]), f"slot {slot}: {key} differs"
    per_key = {}
    for key in made:
        per_key[key] = per_key.get(key, 0) + 1
    assert max(per_key.values()) <= pipeline.IN_FLIGHT + 1, per_key
    print(path.report)


def test_warp_renders_a_store_of_states_as_its_streamed_camera(tmp_path):
    """MuJoCo Warp's renderer on read (every frame of a read batch one world) against the
    Warp engine streaming the same camera: the same float32 states, the same kernels."""
    pytest.importorskip("warp")
    camera = simloader.Camera("back", height=32, width=32)

    def ds(record):
        return simloader.SimDataset("humanoid", backend="warp", nbatch=16, nstep=10,
                                    control=simloader.controls.Uniform(), seed=6, record=record)
    path = simloader.write(ds(("state",)), tmp_path / "s.zarr", batches=1, progress=False)
    streamed = next(iter(ds(("state", camera))))
    stored = simloader.StoredDataset(path, cameras=camera, backend="warp", device="cuda")
    item = stored[5]
    assert item["camera/back/rgb"].is_cuda
    want = streamed["camera/back/rgb"][5]
    differ = (item["camera/back/rgb"].cpu() != want.cpu()).float().mean().item()
    print(f"warp on read: {differ:.2e} of the pixels differ from the stream")
    # the stored states are the streamed ones (float32, the same seed): the same pixels
    assert torch.equal(stored[5]["state"].cpu(), streamed["state"][5].cpu())
    assert differ == 0.0
    transitions = stored.transitions()
    batch = transitions.gather(list(range(0, len(transitions), 3)))
    trajectories, frames = transitions.locate(np.arange(0, len(transitions), 3))
    got = batch["next/camera/back/rgb"].cpu()
    assert torch.equal(got, streamed["camera/back/rgb"][trajectories, frames].cpu())
