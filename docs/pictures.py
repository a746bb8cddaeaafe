"""Makes the pictures of what simloader simulates and renders, for the Pixels page
(`docs/_static/pixels_humanoid.png`): humanoids under random controls, streamed with a
`simloader.Camera` on the CPU engine, four trajectories (rows) at four moments (columns).

    python docs/pictures.py
"""

import pathlib

import numpy as np

import simloader


def main() -> None:
    out = pathlib.Path(__file__).parent / "_static" / "pixels_humanoid.png"
    size = 96
    ds = simloader.SimDataset(
        "humanoid", backend="cpu", nbatch=4, nstep=120, record_every=30, seed=2,
        initial_state=simloader.initial.Perturbed(), control=simloader.controls.Uniform(),
        record=("state", simloader.Camera("back", height=size, width=size)), num_batches=1)
    images = next(iter(ds))["camera/back/rgb"].numpy()  # (4, 4, size, size, 3)
    rows, cols = images.shape[:2]
    picture = images.transpose(0, 2, 1, 3, 4).reshape(rows * size, cols * size, 3)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    plt.imsave(out, np.ascontiguousarray(picture))
    print(f"saved {out} ({out.stat().st_size // 1024} KiB)")


if __name__ == "__main__":
    main()
