"""How a batch maps to Minari episodes (`simloader.store.minari`, "How a batch maps to
episodes"): the batch's arrays checked, one episode buffer a trajectory, the action space."""

from __future__ import annotations

from typing import Any, Iterator, Mapping, Optional

import numpy as np

def check_batch(batch: Any, observation_key: str, index: int,
                shapes: Optional[tuple[int, int]]) -> dict:
    """The arrays of one batch as numpy, with shapes checked against each other (and against
    the first batch's ``(nobs, nact)`` when ``shapes`` is given); ``params`` as a dict of
    ``(n, ...)`` arrays, keys with ``"/"`` written ``"|"`` (an HDF5 name cannot hold one)."""
    where = f"batches[{index}]"
    if not isinstance(batch, Mapping):
        raise ValueError(f"{where}: expected a dict of arrays, got {type(batch).__name__}")
    missing = [k for k in ("initial_state", observation_key, "control", "diverged")
               if k not in batch]
    if missing:
        raise ValueError(f"{where}: expected keys 'initial_state', {observation_key!r} "
                         f"(observation_key), 'control', 'diverged'; missing {missing}, "
                         f"has {sorted(batch)}")
    init = np.asarray(batch["initial_state"])
    obs = np.asarray(batch[observation_key])
    control = np.asarray(batch["control"])
    diverged = np.asarray(batch["diverged"])
    if obs.ndim != 3:
        raise ValueError(f"{where}[{observation_key!r}]: expected shape (n, nstep, nobs), "
                         f"got {obs.shape}")
    n, nstep, nobs = obs.shape
    if init.shape != (n, nobs):
        raise ValueError(f"{where}['initial_state']: expected shape (n, nobs) = {(n, nobs)} "
                         f"to match {observation_key!r} {obs.shape}, got {init.shape}")
    if control.ndim != 3 or control.shape[:2] != (n, nstep):
        raise ValueError(f"{where}['control']: expected shape (n, nstep, nact) with "
                         f"(n, nstep) = {(n, nstep)} from {observation_key!r}, got {control.shape}")
    if diverged.shape != (n,) or diverged.dtype != np.bool_:
        raise ValueError(f"{where}['diverged']: expected a bool array of shape {(n,)}, "
                         f"got {diverged.dtype} {diverged.shape}")
    if n == 0 or nstep == 0:
        raise ValueError(f"{where}[{observation_key!r}]: expected at least one trajectory of at "
                         f"least one step, got shape {obs.shape}")
    if shapes is not None and (nobs, control.shape[2]) != shapes:
        raise ValueError(f"{where}: expected (nobs, nact) = {shapes} as in batches[0], "
                         f"got {(nobs, control.shape[2])}")
    params = batch.get("params") or {}
    if not isinstance(params, Mapping):
        raise ValueError(f"{where}['params']: expected a dict of (n, ...) arrays, "
                         f"got {type(params).__name__}")
    rows = {}
    for key, value in params.items():
        value = np.asarray(value.numpy() if hasattr(value, "numpy") else value)
        if value.ndim < 1 or value.shape[0] != n:
            raise ValueError(f"{where}['params'][{key!r}]: expected shape (n, ...) with n = "
                             f"{n}, got {value.shape}")
        rows[str(key).replace("/", "|")] = value
    out = {"init": init, "obs": obs, "control": control, "diverged": diverged, "params": rows}
    if "first" in batch:  # episodes that end (terminate=): a trajectory holds several
        for key in EPISODE_FLAGS:
            value = np.asarray(batch[key])
            if value.shape != (n, nstep) or value.dtype != np.bool_:
                raise ValueError(f"{where}[{key!r}]: expected a bool array of shape "
                                 f"{(n, nstep)}, got {value.dtype} {value.shape}")
            out[key] = value
    return out


# a batch's flags of episodes that end (`terminate=`), kept with its batch file
EPISODE_FLAGS = ("first", "terminated", "truncated")


def episodes(batch: dict, n: int) -> Iterator[Any]:
    """The first ``n`` trajectories of a checked batch as Minari episode buffers: one per
    trajectory, or with episodes that end (``first`` in the batch) one per episode of it."""
    from minari.data_collector import EpisodeBuffer

    init, obs, control, diverged = batch["init"], batch["obs"], batch["control"], batch["diverged"]
    params = batch.get("params") or {}
    nstep = obs.shape[1]
    for i in range(n):
        for start, stop, terminal, from_initial in _episodes_of(batch, i, nstep):
            # frames start..stop-1 of the trajectory; the first episode starts from the
            # initial state (its frames are the steps after it), a later one from its fresh
            # frame (whose control row was not applied: its steps are the frames after it)
            if from_initial:
                observations = np.concatenate([init[i][None].astype(obs.dtype, copy=False),
                                               obs[i, :stop]])
                actions = control[i, :stop]
            else:
                observations, actions = obs[i, start:stop], control[i, start + 1:stop]
            steps = len(actions)
            if steps == 0:  # a fresh state that met a rule at once: no step to keep
                continue
            terminations = np.zeros(steps, dtype=bool)
            truncations = np.zeros(steps, dtype=bool)
            # Minari's meaning: terminal, the task's end (a rule, or physics that broke on the
            # trajectory's last episode); truncated, cut short (a time limit, or the batch's
            # end)
            last = stop == nstep
            if terminal or (last and diverged[i]):
                terminations[-1] = True
            else:
                truncations[-1] = True
            # Minari's infos are per step (steps + 1 rows, the reset's first): the values the
            # trajectory ran with, on every row
            infos = ({"params": {key: np.repeat(value[i][None], steps + 1, axis=0)
                                 for key, value in params.items()}} if params else {})
            yield EpisodeBuffer(observations=np.array(observations), actions=np.array(actions),
                                rewards=np.zeros(steps), terminations=terminations,
                                truncations=truncations, infos=infos)


def _episodes_of(batch: dict, i: int, nstep: int
                 ) -> Iterator[tuple[int, int, bool, bool]]:
    """(start, stop, terminal, from_initial) of each episode of trajectory `i`: its frames
    start..stop-1, whether a terminating rule ended it, and whether it starts from the
    batch's initial state (else from its fresh frame `start`)."""
    if "first" not in batch:
        yield 0, nstep, False, True
        return
    fresh = [int(f) for f in np.flatnonzero(batch["first"][i])]
    # without a fresh frame 0, the first episode starts from the batch's initial state (with
    # continue_episodes a trajectory may start the batch at a fresh frame instead)
    starts = ([] if fresh and fresh[0] == 0 else [0]) + fresh
    for k, start in enumerate(starts):
        stop = starts[k + 1] if k + 1 < len(starts) else nstep
        from_initial = k == 0 and start not in fresh
        yield start, stop, bool(batch["terminated"][i][stop - 1]), from_initial


def applied_action_bounds(config: Any) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of each control column: what MuJoCo clamps it to, the widest over the
    models of the pool; unbounded for actuators whose ctrlrange is randomized."""
    import mujoco

    from simloader import controls
    low, high = controls.applied_bounds(config.pool, config.control_spec)
    low, high = np.min(low, axis=0), np.max(high, axis=0)
    if config.randomization is not None and \
            config.control_spec & int(mujoco.mjtState.mjSTATE_CTRL):
        for r in config.randomization.resolved:
            if r.field == "actuator_ctrlrange":  # ctrl comes first in a control row
                actuators = np.unique(np.asarray(r.elements) // 2)
                low[actuators], high[actuators] = -np.inf, np.inf
    return low, high


def action_space(bounds: Optional[tuple[Any, Any]], nact: int, dtype: Any) -> Any:
    from gymnasium.spaces import Box
    if bounds is None:
        return Box(-np.inf, np.inf, (nact,), dtype)
    low, high = (np.asarray(b, dtype=np.float64) for b in bounds)
    if low.shape != (nact,) or high.shape != (nact,) or np.any(low > high):
        raise ValueError(f"action_bounds: expected (low, high) of shape ({nact},) each (the "
                         f"batches' control columns) with low <= high, got shapes "
                         f"{low.shape} and {high.shape}")
    return Box(low.astype(dtype), high.astype(dtype), (nact,), dtype)
