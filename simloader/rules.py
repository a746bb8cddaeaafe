"""The step rules every engine applies, written once over an array module (`xp`: NumPy, JAX's
`jax.numpy` or torch): what counts as unstable (beyond mjMAXVAL), how an unstable trajectory
restarts, whether a recorded frame is finite, and which frame a step records into. The control
rules (bad controls, MuJoCo's clamp) live beside the control generators, in `controls.py`.
"""

from __future__ import annotations

from typing import Any

# mjMAXVAL: MuJoCo's bound for a sane value (its checks of qpos, qvel, qacc and ctrl)
MAXVAL = 1e10

# the fields `restart_unstable` leaves finite in every trajectory (a recorded value made only
# of these needs no second finiteness check)
RESTARTED = frozenset(("time", "qpos", "qvel", "act", "sensordata"))


def unstable(time: Any, qpos: Any, qvel: Any, act: Any, qacc: Any, sensordata: Any,
             xp: Any) -> Any:
    """(nbatch,) bool: trajectories MuJoCo would call unstable after a step (a value beyond
    mjMAXVAL, NaN or Inf in time, qpos, qvel, act or qacc), or with a non-finite sensor.
    Arguments are (nbatch, ...) arrays of module `xp` (time (nbatch,) or (nbatch, 1))."""
    cat = xp.cat if hasattr(xp, "cat") else xp.concatenate
    n = qpos.shape[0]
    checked = cat([time.reshape(n, 1), qpos, qvel, act, qacc], 1)
    # NaN compares False, so `<=` catches NaN, Inf and huge values at once
    stable = (abs(checked) <= MAXVAL).all(1) & xp.isfinite(sensordata).all(1)
    return ~stable


# what a step reads of the previous one (its inputs aside, which are set before every step),
# restarted as mj_resetData leaves them: qpos at qpos0, the others zero
RESET = ("time", "qpos", "qvel", "act", "qacc_warmstart", "sensordata")


def restart_unstable(fields: dict[str, Any], qpos0: Any, xp: Any) -> tuple[dict[str, Any], Any]:
    """Flags the trajectories of batched `fields` ({name: (nbatch, ...) arrays of `xp`}: time,
    qpos, qvel, act, qacc, qacc_warmstart, sensordata) that went `unstable`, and restarts their
    `RESET` fields as mj_resetData leaves them, `qpos0` ([nbatch or 1] x nq) for qpos. As
    MuJoCo does: their NaNs are never delivered, and the solver loops of a whole batch, which
    run until every trajectory converges, do not keep iterating on them. (MJX's; the Warp
    engine does the same in its own kernel, `backends/warp/fused.py`.)

    Returns:
      (fields with the restarted rows, new arrays; (nbatch,) bool: the rows that restarted).
    """
    f = fields
    bad = unstable(f["time"], f["qpos"], f["qvel"], f["act"], f["qacc"], f["sensordata"], xp)
    out = dict(f)
    for name in RESET:
        x = f[name]
        rows = bad.reshape((-1,) + (1,) * (x.ndim - 1))
        out[name] = xp.where(rows, qpos0 if name == "qpos" else 0, x)
    return out, bad


def finite(values: Any, xp: Any) -> Any:
    """(nbatch,) bool: every value of the batched arrays `values` ((nbatch, ...) each, of
    module `xp`) is finite, or None for no value; a recorded frame's check for the
    divergence flag."""
    out = None
    for value in values:
        ok = xp.isfinite(value.reshape(value.shape[0], -1)).all(1)
        out = ok if out is None else out & ok
    return out


def frame_index(t: Any, every: int) -> Any:
    """The frame step `t` (0-based) records into with `record_every=every`: every step of a
    group writes its frame, the due one (the group's last) last."""
    return t // every


def frame_due(t: Any, every: int) -> Any:
    """Whether step `t` (0-based) ends its group of `every`: the state after it is the one
    its frame (`frame_index`) records."""
    return t % every == every - 1
