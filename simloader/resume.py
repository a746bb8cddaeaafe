"""Checkpointing a stream: `SimDataset.state_dict()` / `load_state_dict()`.

A stream is determined by its configuration and the index of the next batch; with
`continue_episodes` also by where every trajectory is (its `mjSTATE_INTEGRATION` row, solver
warmstart included), stored bit-exactly as base64 so that the state stays JSON-serializable.
"""

from __future__ import annotations

import base64
import hashlib
from typing import Any

import mujoco
import numpy as np

from simloader.config import SimConfig

VERSION = 2  # 2: continuing checkpoints carry the randomized values and variants


def encode_array(array: np.ndarray) -> dict[str, Any]:
    """A JSON-serializable, bit-exact encoding of an array."""
    array = np.ascontiguousarray(array)
    return {"dtype": array.dtype.str, "shape": list(array.shape),
            "data": base64.b64encode(array.tobytes()).decode("ascii")}


def decode_array(encoded: dict[str, Any]) -> np.ndarray:
    raw = base64.b64decode(encoded["data"])
    return np.frombuffer(raw, dtype=np.dtype(encoded["dtype"])).reshape(encoded["shape"]).copy()


def _model_digest(model: mujoco.MjModel) -> str:
    buffer = np.empty(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return hashlib.sha256(buffer.tobytes()).hexdigest()[:16]


def fingerprint(config: SimConfig) -> dict[str, Any]:
    """What must match for a saved stream to resume: sizes, seed, backend and the model."""
    models = config.models or (config.model,)
    return {
        "backend": config.backend, "nbatch": config.nbatch, "nstep": config.nstep,
        "control_spec": config.control_spec, "seed": config.seed,
        "continue_episodes": config.continue_episodes, "num_batches": config.num_batches,
        "record": [o.key for o in config.observations], "record_every": config.record_every,
        "model": hashlib.sha256("".join(_model_digest(m) for m in models).encode()).hexdigest()[:16],
    }


def check(config: SimConfig, state: Any) -> None:
    """Raises ValueError unless `state` is a state_dict of a stream with this configuration."""
    if not isinstance(state, dict) or state.get("version") != VERSION:
        raise ValueError(f"state_dict: expected a simloader state of version {VERSION}, got "
                         f"{state if not isinstance(state, dict) else state.get('version')!r}")
    expected, saved = fingerprint(config), state.get("config", {})
    diff = [f"{k} is {expected[k]!r} here but {saved.get(k)!r} in the state"
            for k in expected if saved.get(k) != expected[k]]
    if diff:
        raise ValueError("state_dict: the saved stream has another configuration: "
                         + "; ".join(diff))
