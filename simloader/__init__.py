"""simloader: freshly simulated MuJoCo trajectories, streamed into PyTorch.

    ds = simloader.SimDataset("cartpole", nbatch=4096, nstep=200,
                              control=simloader.controls.Uniform())
    for batch in torch.utils.data.DataLoader(ds, batch_size=None):
        batch["state"]  # (4096, 200, nstate)

The public names load on first use (PEP 562), so `import simloader` and `simloader --version`
do not import torch and MuJoCo before they are needed.
"""

from __future__ import annotations

import importlib.util
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name -> the module that defines it (a module's own name: the module itself)
_WHERE = {
    "Batch": "simloader.batch",
    "Camera": "simloader.observe",
    "KnownFaultWarning": "simloader.known_faults",
    "Mixture": "simloader.mixture",
    "SimDataset": "simloader.dataset",
    "StoredDataset": "simloader.store",
    "builtin_models": "simloader.models",
    "builtin_path": "simloader.models",
    "controls": "simloader.controls",
    "describe": "simloader.models",
    "initial": "simloader.initial",
    "layout": "simloader.layout",
    "load_model": "simloader.models",
    "named_models": "simloader.models",
    "observe": "simloader.observe",
    "open_store": "simloader.store",
    "policy": "simloader.policy",
    "randomize": "simloader.randomize",
    "video": "simloader.videos",
    "write": "simloader.store",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> object:
    where = _WHERE.get(name)
    if where is None:
        # a submodule (`simloader.store.formats`, `simloader.backends`): as reachable as when
        # this package imported everything up front
        if not name.startswith("_") and importlib.util.find_spec(f"simloader.{name}"):
            return importlib.import_module(f"simloader.{name}")
        raise AttributeError(f"module 'simloader' has no attribute {name!r}")
    module = importlib.import_module(where)
    value = module if where == f"simloader.{name}" else getattr(module, name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(__all__) | {"__version__"})


if TYPE_CHECKING:  # what type checkers and IDEs see
    from simloader import controls, initial, layout, observe, policy, randomize
    from simloader.batch import Batch
    from simloader.dataset import SimDataset
    from simloader.known_faults import KnownFaultWarning
    from simloader.mixture import Mixture
    from simloader.observe import Camera
    from simloader.store import StoredDataset, open_store, write
    from simloader.videos import video
    from simloader.models import (builtin_models, builtin_path, describe, load_model,
                                  named_models)
