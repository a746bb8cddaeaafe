"""MuJoCo's own warnings, counted instead of printed.

MuJoCo prints every warning (a diverging trajectory: "Nan, Inf or huge value in QACC ...") to
stderr and appends it to `MUJOCO_LOG.TXT` in the working directory. A stream of thousands of
trajectories would print a line for every one that diverges, and leave a log file behind,
while simloader already flags each one in `batch["diverged"]` and counts them in
`ds.stats["diverged"]`. So while a simloader backend runs, MuJoCo's warning handler counts the
messages; the first time any arrive, one Python warning says how many and what the first one
was. When the last backend of the process closes (the stream ended, was broken out of and
closed, or was written), MuJoCo's own handler is given back: the user's own `mj_step`
warnings reach stderr and `MUJOCO_LOG.TXT` again. (While a backend runs, a warning of the
user's own `mj_step` in the same process is counted with simloader's: MuJoCo has one handler
per process.) A handler the user installed (`mujoco.set_mju_user_warning`) is left alone: it
gets every message as before.
"""

from __future__ import annotations

import threading
import warnings

import mujoco

_LOCK = threading.Lock()
_COUNT = 0
_FIRST = ""
_SAID = False
_INSTALLED = False  # simloader's counter is MuJoCo's handler
_HOLDERS = 0  # backends alive that asked for it


def _count(message: str) -> None:
    # called from MuJoCo's threads (mujoco.batch), with the GIL
    global _COUNT, _FIRST
    with _LOCK:
        _COUNT += 1
        _FIRST = _FIRST or message.strip()


def install() -> None:
    """Counts MuJoCo's warnings from now until the matching `release`, unless the user
    installed a handler."""
    global _INSTALLED, _HOLDERS
    with _LOCK:
        _HOLDERS += 1
        if _INSTALLED or mujoco.get_mju_user_warning() is not None:
            return
        mujoco.set_mju_user_warning(_count)
        _INSTALLED = True


def release() -> None:
    """The end of an `install`: the last one gives MuJoCo its own handler back."""
    global _INSTALLED, _HOLDERS
    with _LOCK:
        _HOLDERS = max(0, _HOLDERS - 1)
        if _HOLDERS == 0 and _INSTALLED:
            mujoco.set_mju_user_warning(None)
            _INSTALLED = False


def count() -> int:
    """MuJoCo warnings counted in this process so far."""
    return _COUNT


def summarize(stacklevel: int = 3) -> None:
    """Once per process, when MuJoCo has warned: one Python warning with the count and the
    first message (the trajectories themselves are flagged in `diverged`)."""
    global _SAID
    if _SAID or not _COUNT:
        return
    _SAID = True
    warnings.warn(f"simloader: MuJoCo warned {_COUNT} time(s) so far, first: {_FIRST!r}; the "
                  f"trajectories concerned are flagged in batch['diverged'] and counted in "
                  f"stats['diverged'], and MuJoCo's messages are counted rather than printed "
                  f"(install your own handler with mujoco.set_mju_user_warning to see each)",
                  RuntimeWarning, stacklevel=stacklevel)
