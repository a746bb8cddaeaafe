"""The DataLoader simloader hands out: torchdata's `StatefulDataLoader`, which resumes, with
a state saved under another number of workers refused by name when it is loaded.

torchdata saves a loader's state in one of two layouts: a single-process loader's
(`num_workers=0`: its counters at the top level) or a multi-process one's (`_snapshot`, whose
`_main_snapshot` holds `_num_workers`, and one state per worker). Loaded into a loader of
another count it fails only at the next iteration, in one of torchdata's `assert`s, with no
word of workers. Each worker's place in the stream is its own part of the state, so no count
but the saved one can resume it.

Without torchdata the loader is torch's `DataLoader`, which neither saves nor resumes.
"""

from __future__ import annotations

from typing import Any, Optional

import torch

# torchdata's keys (torchdata 0.11, `stateful_dataloader.py`: the multi-process iterator's
# `_SNAPSHOT`, `_MAIN_SNAPSHOT` and `_NUM_WORKERS`, the single-process one's `_NUM_YIELDED`)
_SNAPSHOT, _MAIN, _NUM_WORKERS, _SINGLE = ("_snapshot", "_main_snapshot", "_num_workers",
                                           "_num_yielded")


def _saved_workers(state: Any) -> Optional[int]:
    """The `num_workers` of the loader that saved `state` (a `state_dict()`), or None where
    `state` is no loader state of torchdata's (an empty one included)."""
    if not isinstance(state, dict):
        return None
    if isinstance(state.get(_SNAPSHOT), dict):
        count = (state[_SNAPSHOT].get(_MAIN) or {}).get(_NUM_WORKERS)
        return count if isinstance(count, int) and not isinstance(count, bool) else None
    return 0 if _SINGLE in state else None


try:
    from torchdata.stateful_dataloader import StatefulDataLoader as _Stateful
except ImportError:  # no torchdata: torch's own loader, which does not resume
    StatefulDataLoader: Any = torch.utils.data.DataLoader
else:
    class StatefulDataLoader(_Stateful):  # type: ignore[no-redef]
        """torchdata's `StatefulDataLoader`, whose `load_state_dict` checks first that the
        state was saved with this loader's `num_workers` (see the module's docstring)."""

        def load_state_dict(self, state_dict: dict[str, Any]) -> None:
            """Resumes from `state_dict` (a `state_dict()` of a loader made the same way) at
            the next iteration; `{}` resumes nothing (torchdata's meaning).

            Raises:
              ValueError: not a loader's state, or one saved with another `num_workers`
                (saying both and what to do).
            """
            if state_dict != {}:
                _check(state_dict, self.num_workers)
            super().load_state_dict(state_dict)


def _check(state: Any, num_workers: int) -> None:
    """Refuses what is no loader's state, or one saved with other than `num_workers`."""
    saved = _saved_workers(state)
    if saved is None:
        got = (f"a dict of keys {sorted(map(str, state))}" if isinstance(state, dict)
               else type(state).__name__)
        raise ValueError(f"load_state_dict: expected a StatefulDataLoader's state_dict(), got "
                         f"{got}")
    if saved != num_workers:
        raise ValueError(f"load_state_dict: the state was saved by a loader with "
                         f"num_workers={saved}, this loader has num_workers={num_workers}; "
                         f"each worker's place is saved apart, so make the loader with "
                         f"num_workers={saved} as when saved (the other arguments too) to "
                         f"resume")
