"""What a store says of its trajectories: the configuration, seed and library versions that
made them, and whether a dataset is that configuration."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import uuid
from typing import Any, Optional

from simloader import identity, known_faults
from simloader.store.zarr_format import FORMAT


def versions() -> dict[str, Optional[str]]:
    """The versions of the libraries a stored stream depends on (None: not installed)."""
    out = {}
    for name in ("simloader", "mujoco", "mujoco-mjx", "jax", "mujoco-warp", "warp-lang",
                 "torch", "numpy"):
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


# the versions whose change changes the simulated values (a stale store must not be resumed
# by another build of the simulator)
SIMULATING = ("simloader", "mujoco", "mujoco-mjx", "jax", "mujoco-warp", "warp-lang")


def fingerprint(dataset: Any) -> dict:
    """What must match to append to a store or regenerate from it: the configuration's identity
    without `num_batches` (the store's size is `batches`)."""
    out = dict(identity.fingerprint(dataset.config))
    out.pop("num_batches")
    return out


def differences(stored: dict, mine: dict) -> list[str]:
    """What differs between a store's fingerprint and a dataset's, each setting named (down
    to the field of a nested one), as the resume check names them."""
    return [f"{k}: stored {identity.short(there)}, given {identity.short(here)}"
            for k, here, there in identity.differences(mine, identity.upgraded(stored))]


def provenance(dataset: Any, batches: int) -> dict:
    """The store's root attribute: what made it, and how to make it again."""
    from simloader.store.pixels import pool_of
    c = dataset.config
    kind, pool = pool_of(c)
    return {"format": FORMAT, "fingerprint": fingerprint(dataset),
            "describe": dataset.describe(), "seed": c.seed, "nbatch": c.nbatch,
            "nstep": c.nstep, "record_every": c.record_every, "batches": batches,
            "versions": versions(),
            # the models it simulated, kept as MJB files (`pixels.save_models`): a store of
            # states renders its cameras on read with them
            "models": {"kind": kind, "count": len(pool)},
            # the simulator's known faults this stream met (`known_faults`): flagged at open
            "known_faults": known_faults.recorded(dataset)}


def fingerprint_digest(fingerprint: Any) -> str:
    """A short digest of a fingerprint as a store's root keeps it (JSON: lists and tuples
    alike), for a mixture's root to name its members' configurations."""
    text = json.dumps(fingerprint, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def new_identity() -> str:
    """A new store's identity, kept in its root while it grows: a reader holds the one it
    opened, and a store written anew at the same path (`replace=True`) has another."""
    return uuid.uuid4().hex


class StoreMismatch(ValueError):
    """An existing store holds another configuration (or simulator build) than the dataset."""

