"""One bookkeeping of a batch's trajectories for the engines that keep it between batches
outside a compiled function (the CPU engine on the host in NumPy, MuJoCo Warp on its device in
torch): which trajectories start afresh at the next batch, which model of the pool each runs
on, the randomized values each runs with, and the checkpoint of all three with the state rows.
(MJX keeps the same inside its jitted batch function, as its carry.)

Trajectories start afresh at every batch, or with `continue_episodes` only where the last
batch diverged; those take their newly drawn variant and values (`take`), the others keep
theirs.
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from simloader import layout, resume


class Trajectories:
    """A batch's trajectories as the next batch starts them.

    Args:
      config: the dataset's configuration (`nbatch`, `models`, `continue_episodes`).
      device: None to keep everything in NumPy, or the torch device to keep it on.

    Attributes:
      fresh: (nbatch,) bool, the trajectories that start afresh at the next batch.
      params: {key: (nbatch, ...)}, what each trajectory runs with: "variant" (the index of
        its variant) and each randomized parameter's values; empty without either.
      model_index: (nbatch,) int, each trajectory's model of `config.pool` (its variant, its
        entry of a model list, or 0).
    """

    def __init__(self, config: Any, device: Optional[Any] = None):
        n = config.nbatch
        self.continuing = config.continue_episodes
        self.listed = config.models is not None  # a model list: one model per trajectory
        self.device = device
        if device is None:
            self.xp = np
            self.fresh = np.ones(n, dtype=bool)
            self.model_index = (np.arange(n) if config.models is not None
                                else np.zeros(n, dtype=np.int64))
        else:
            import torch
            self.xp = torch
            self.fresh = torch.ones(n, dtype=torch.bool, device=device)
            self.model_index = (torch.arange(n, device=device) if config.models is not None
                                else torch.zeros(n, dtype=torch.int64, device=device))
        self.params: dict[str, Any] = {}

    def _rows(self, value: Any) -> Any:
        """`fresh` shaped to select whole rows of `value`."""
        return self.fresh.reshape(-1, *([1] * (value.ndim - 1)))

    def take(self, drawn: dict[str, Any]) -> None:
        """The trajectories that start afresh take their newly drawn variant and values
        (`drawn`: {key: (nbatch, ...)} in this bookkeeping's array library); the others keep
        what they ran with."""
        for key, value in drawn.items():
            old = self.params.get(key, value)
            self.params[key] = self.xp.where(self._rows(value), value, old)
        if "variant" in self.params:
            self.model_index = self.params["variant"]

    def per_trajectory(self, table: Any) -> Any:
        """(nbatch, ...): each trajectory's row of a per-model table ((1 or npool, ...))."""
        n = len(self.fresh)
        if table.shape[0] == 1:
            return (np.broadcast_to(table, (n, *table.shape[1:])) if self.xp is np
                    else table.expand(n, *table.shape[1:]))
        if self.listed:  # row i is trajectory i's already: no gather (and no copy) per batch
            return table
        return table[self.model_index]

    def finished(self, diverged: Any) -> None:
        """After a batch: every trajectory starts afresh at the next, or with
        `continue_episodes` only the `diverged` ones ((nbatch,) bool)."""
        self.fresh = diverged if self.continuing else self.xp.ones_like(self.fresh)

    def checkpoint(self, rows: Any, fresh: Any, params: dict[str, Any]) -> dict[str, Any]:
        """The JSON-serializable record of continuing trajectories after a batch: their
        mjSTATE_INTEGRATION `rows`, the `fresh` flags and `params` that batch left."""
        return resume.encode_trajectories(layout.INTEGRATION, _host(rows), _host(fresh),
                                          {k: _host(v) for k, v in params.items()})

    def restore(self, trajectories: dict[str, Any]) -> Any:
        """Continues from a `checkpoint`: its flags and values taken, its state rows
        returned (nbatch, nintegration) for the engine to load."""
        rows, fresh, params = resume.decode_trajectories(trajectories, layout.INTEGRATION)
        if self.xp is np:
            self.fresh, self.params = fresh, params
        else:
            to = dict(device=self.device)
            self.fresh = self.xp.as_tensor(fresh, **to)
            self.params = {k: self.xp.as_tensor(v, **to) for k, v in params.items()}
            rows = self.xp.as_tensor(rows, **to)
        if "variant" in self.params:
            self.model_index = self.params["variant"]
        return rows


def _host(array: Any) -> np.ndarray:
    """A NumPy array of a NumPy array or a torch tensor (copied from its device)."""
    return array if isinstance(array, np.ndarray) else array.cpu().numpy()
