"""simloader: freshly simulated MuJoCo trajectories, streamed into PyTorch.

    ds = simloader.SimDataset("cartpole", nbatch=4096, nstep=200,
                              control=simloader.controls.Uniform())
    for batch in torch.utils.data.DataLoader(ds, batch_size=None):
        batch["state"]  # (4096, 200, nstate)
"""

from simloader import controls, initial, layout, observe, policy, randomize
from simloader.batch import Batch
from simloader.dataset import SimDataset
from simloader.known_faults import KnownFaultWarning
from simloader.mixture import Mixture
from simloader.observe import Camera
from simloader.store import StoredDataset, write
from simloader.videos import video
from simloader.models import builtin_models, builtin_path, describe, load_model, named_models

__version__ = "0.1.0"

__all__ = [
    "Batch",
    "Camera",
    "KnownFaultWarning",
    "Mixture",
    "SimDataset",
    "StoredDataset",
    "builtin_models",
    "builtin_path",
    "controls",
    "describe",
    "initial",
    "layout",
    "load_model",
    "named_models",
    "observe",
    "policy",
    "randomize",
    "video",
    "write",
]
