"""Checkpointing a stream: `SimDataset.state_dict()` / `load_state_dict()`.

A stream is determined by its configuration and the index of the next batch; with
`continue_episodes` also by where every trajectory is (its `mjSTATE_INTEGRATION` row, solver
warmstart included), stored bit-exactly as base64 so that the state stays JSON-serializable.
"""

from __future__ import annotations

import base64
from typing import Any, Callable, Optional

import numpy as np

from simloader.config import SimConfig
from simloader.identity import differences, fingerprint, short, upgraded

# 2: continuing checkpoints carry the randomized values and variants; 3: the configuration
# covers control, initial state, randomization, dtype, options; 4: and whether a policy (and
# its noise) picks the controls; 5: continuing trajectories are one structure on every engine
# (`encode_trajectories`)
VERSION = 5


def encode_array(array: np.ndarray) -> dict[str, Any]:
    """A JSON-serializable, bit-exact encoding of an array."""
    array = np.ascontiguousarray(array)
    return {"dtype": array.dtype.str, "shape": list(array.shape),
            "data": base64.b64encode(array.tobytes()).decode("ascii")}


def decode_array(encoded: dict[str, Any]) -> np.ndarray:
    raw = base64.b64decode(encoded["data"])
    return np.frombuffer(raw, dtype=np.dtype(encoded["dtype"])).reshape(encoded["shape"]).copy()


def encode_trajectories(spec: int, rows: np.ndarray, fresh: np.ndarray,
                        params: dict[str, np.ndarray]) -> dict[str, Any]:
    """What continuing trajectories carry into the next batch, one structure on every engine:
    their state rows ((nbatch, n), mjtState `spec`: the engine's own state), which of them
    start afresh ((nbatch,) bool: diverged ones), and the randomized values and variants they
    run with ({key: (nbatch, ...)})."""
    return {"spec": int(spec), "rows": encode_array(rows), "fresh": encode_array(fresh),
            "params": {k: encode_array(v) for k, v in params.items()}}


def decode_trajectories(encoded: dict[str, Any],
                        spec: int) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(rows, fresh, params) of `encode_trajectories`, whose rows must be of mjtState `spec`."""
    if encoded.get("spec") != int(spec):
        raise ValueError(f"state_dict: the continuing trajectories hold state rows of mjtState "
                         f"spec {encoded.get('spec')}, this engine resumes from spec {int(spec)}")
    return (decode_array(encoded["rows"]), decode_array(encoded["fresh"]),
            {k: decode_array(v) for k, v in encoded["params"].items()})


def encode_episodes(pending: np.ndarray, steps: np.ndarray) -> dict[str, Any]:
    """What continuing episodes (`terminate=`) carry into the next batch: the rows whose last
    frame met a rule (their next frame is a fresh state) and each episode's steps so far."""
    return {"pending": encode_array(np.asarray(pending, bool)),
            "steps": encode_array(np.asarray(steps, np.int64))}


def decode_episodes(encoded: dict[str, Any], nbatch: int) -> tuple[np.ndarray, np.ndarray]:
    """(pending, steps) of `encode_episodes` in a trajectories record; none pending and no
    steps where the record has none."""
    if "episodes" not in encoded:
        return np.zeros(nbatch, bool), np.zeros(nbatch, np.int64)
    return (decode_array(encoded["episodes"]["pending"]),
            decode_array(encoded["episodes"]["steps"]))


def check(config: SimConfig, state: Any) -> None:
    """Raises ValueError unless `state` is a state_dict of a stream with this configuration,
    naming the differences."""
    if not isinstance(state, dict) or state.get("version") != VERSION:
        raise ValueError(f"state_dict: expected a simloader state of version {VERSION}, got "
                         f"{state if not isinstance(state, dict) else state.get('version')!r}")
    diff = [f"{k} is {short(here)} here but {short(there)} in the state"
            for k, here, there in differences(fingerprint(config),
                                              upgraded(state.get("config", {})))]
    if diff:
        more = f"; and {len(diff) - 6} more" if len(diff) > 6 else ""
        raise ValueError("state_dict: the saved stream has another configuration: "
                         + "; ".join(diff[:6]) + more)


class Position:
    """Where one iterator of a stream is, for `state_dict()`: what `SimDataset` and `Mixture`
    share. A loaded state is taken by `iter()` (`start`), not by the first `next()`: a
    loader may make an iterator and drop it unstarted (torchdata's `StatefulDataLoader` does
    when it resumes from the end of an epoch), and the next iterator must start the next
    epoch, not find it again. A copy sent to a DataLoader worker starts its own iteration:
    the running iterator's progress stays behind (`__getstate__`)."""

    def __init__(self) -> None:
        self.loaded: Optional[dict] = None  # a state_dict to resume from at the next iter()
        self.pending: Optional[dict] = None  # the one the current iterator resumes from
        self.progress: Any = None  # what the current iterator delivered up to (its own)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "progress": None}

    def load(self, state: dict) -> None:
        self.loaded, self.pending, self.progress = state, None, None

    def start(self, shard: Any, where: str) -> Optional[dict]:
        """At `iter()`: the loaded state if it holds a position (its key `where` not None) and
        was saved by this shard's worker and rank, None to start afresh.

        Raises:
          ValueError: the state was saved by another worker, worker count or rank."""
        loaded, self.loaded = self.loaded, None
        self.pending, self.progress = loaded, None
        if loaded is None or loaded.get(where) is None:
            return None
        saved = [shard.worker, shard.num_workers, shard.rank]
        if loaded["shard"] != saved:
            raise ValueError(f"state_dict: saved by worker/num_workers/rank {loaded['shard']}, "
                             f"resumed as {saved}")
        return loaded

    def saved(self, initial: Callable[[], dict]) -> Optional[dict]:
        """The state to save when nothing was delivered since the last load or `iter()`
        (`initial()`: a stream's state at its start), or None once something was."""
        if self.progress is not None:
            return None
        return self.loaded or self.pending or initial()
