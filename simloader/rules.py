"""The step rules every engine applies, written once over an array module (`xp`: NumPy, JAX's
`jax.numpy` or torch): what counts as unstable, how an unstable trajectory restarts, and which
frame a step records into. The control rules (bad controls, MuJoCo's clamp) live beside the
control generators, in `controls.py`.
"""

from __future__ import annotations

from typing import Any

from simloader.controls import MAXVAL

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


def restart_unstable(fields: dict[str, Any], qpos0: Any, xp: Any) -> Any:
    """Restarts, in place, the trajectories of MuJoCo Warp-style `fields` ({name: (nbatch,
    ...) torch tensors}) that went unstable, as mj_resetData leaves them (time 0, qpos at
    `qpos0` ([nbatch or 1] x nq), zero velocities, activations, warmstart and sensors).
    A few fused kernels per step (one comparison, masked writes). Returns the (nbatch,) rows
    that restarted."""
    f = fields
    bad = unstable(f["time"], f["qpos"], f["qvel"], f["act"], f["qacc"], f["sensordata"], xp)
    rows = bad[:, None]
    f["time"].masked_fill_(bad.reshape(f["time"].shape), 0)
    xp.where(rows, qpos0, f["qpos"], out=f["qpos"])
    for name in ("qvel", "act", "qacc_warmstart", "sensordata"):
        f[name].masked_fill_(rows, 0)
    return bad


def frame_index(t: Any, every: int) -> Any:
    """The frame step `t` (0-based) records into with `record_every=every`: every step of a
    group writes its frame, the due one (the group's last) last."""
    return t // every
