"""The Warp engine's own work around MuJoCo Warp's step, as Warp kernels.

On a cheap model every launch of the step graph shows: the cart-pole's step is about 300
microseconds for 8192 worlds, and each small torch operation adds a launch and its gap (the
divergence check and restart alone were about fifteen of them). So the engine's work between
two control rows is a few launches besides MuJoCo Warp's own, each of one thread per value
where the work is per value (a thread per world looping over its columns in sequence is latency
no step hides):

- `Inputs.launch`, before the step: step `t`'s control row of every world (the driver's
  (nbatch, nstep, ncontrol) rows; a world an episode holds at its fresh state takes the inputs
  mj_resetData leaves) into MuJoCo Warp's input arrays, one launch per input array;
- `AfterStep.launch`, after it: MuJoCo's divergence check (`rules.unstable`, the same tests in
  the same float32 arithmetic, one thread per value), the restart of the worlds it flags
  (`rules.restart_unstable`) and a held world back at its fresh state (one thread per world),
  then the frame of a `state` record and of each record that is a run of columns of one
  array (one thread per column);
- the step index's increment (a torch operation).

Records of any other shape (an int32 count, say) are read by torch as before
(`observe.value`), after these kernels.
"""

from __future__ import annotations

from typing import Any, Optional

import torch
import warp as wp

from simloader import records as records_, rules
from simloader.backends.warp import observe as warp_observe
from simloader.backends.warp.episodes import set_state

MAXVAL = wp.constant(wp.float32(rules.MAXVAL))  # exact in float32 (9765625 * 2**10)


@wp.kernel
def _inputs(t: wp.array(dtype=wp.int64), rows: wp.array3d(dtype=wp.float32), start: int,
            held: wp.array(dtype=wp.bool), reset: wp.array2d(dtype=wp.float32),
            target: wp.array2d(dtype=wp.float32)):
    """target[w, j] = column `start + j` of world w's row at step t (of its reset inputs while
    an episode holds it)."""
    w, j = wp.tid()
    if held.shape[0] > 0 and held[w]:
        target[w, j] = reset[w, start + j]
    else:
        target[w, j] = rows[w, int(t[0]), start + j]


@wp.kernel
def _inputs_bool(t: wp.array(dtype=wp.int64), rows: wp.array3d(dtype=wp.float32), start: int,
                 held: wp.array(dtype=wp.bool), reset: wp.array2d(dtype=wp.float32),
                 target: wp.array2d(dtype=wp.bool)):
    """As `_inputs`, into a boolean array (`eq_active`: a non-zero column is on)."""
    w, j = wp.tid()
    if held.shape[0] > 0 and held[w]:
        target[w, j] = reset[w, start + j] != 0.0
    else:
        target[w, j] = rows[w, int(t[0]), start + j] != 0.0


@wp.func
def _sane(x: wp.float32) -> bool:
    # NaN compares False: NaN, Inf and values beyond mjMAXVAL at once, as `rules.unstable`
    return wp.abs(x) <= MAXVAL


@wp.kernel
def _check(time: wp.array(dtype=wp.float32), qpos: wp.array2d(dtype=wp.float32),
           qvel: wp.array2d(dtype=wp.float32), qacc: wp.array2d(dtype=wp.float32),
           act: wp.array2d(dtype=wp.float32), sensordata: wp.array2d(dtype=wp.float32),
           bad: wp.array(dtype=wp.bool), diverged: wp.array(dtype=wp.bool)):
    """MuJoCo's divergence check of one value of world w after the step (`rules.unstable`):
    column j of (time, qpos, qvel, qacc, act, sensordata) laid end to end; a bad value sets
    the world's `bad` (this step's) and `diverged` (the batch's) flags."""
    w, j = wp.tid()
    nq, nv, na = qpos.shape[1], qvel.shape[1], act.shape[1]
    ok = bool(True)
    if j == 0:
        ok = _sane(time[w])
    elif j < 1 + nq:
        ok = _sane(qpos[w, j - 1])
    elif j < 1 + nq + nv:
        ok = _sane(qvel[w, j - 1 - nq])
    elif j < 1 + nq + 2 * nv:
        ok = _sane(qacc[w, j - 1 - nq - nv])
    elif j < 1 + nq + 2 * nv + na:
        ok = _sane(act[w, j - 1 - nq - 2 * nv])
    else:
        ok = wp.isfinite(sensordata[w, j - 1 - nq - 2 * nv - na])
    if not ok:  # every writer writes True: no race
        bad[w] = True
        diverged[w] = True


@wp.kernel
def _restart(qpos0: wp.array2d(dtype=wp.float32), time: wp.array(dtype=wp.float32),
             qpos: wp.array2d(dtype=wp.float32), qvel: wp.array2d(dtype=wp.float32),
             act: wp.array2d(dtype=wp.float32), warmstart: wp.array2d(dtype=wp.float32),
             sensordata: wp.array2d(dtype=wp.float32), bad: wp.array(dtype=wp.bool),
             held: wp.array(dtype=wp.bool), at: wp.array2d(dtype=wp.float32)):
    """A world `_check` found bad restarted as mj_resetData leaves it (`rules.RESET`), its
    flag cleared for the next step; a world an episode holds back at its fresh state. Only
    those worlds loop over their columns: the others read two flags."""
    w = wp.tid()
    nq, nv, na = qpos.shape[1], qvel.shape[1], act.shape[1]
    if bad[w]:
        bad[w] = False
        row = w
        if qpos0.shape[0] == 1:
            row = 0
        time[w] = 0.0
        for i in range(nq):
            qpos[w, i] = qpos0[row, i]
        for i in range(nv):
            qvel[w, i] = 0.0
            warmstart[w, i] = 0.0
        for i in range(na):
            act[w, i] = 0.0
        for i in range(sensordata.shape[1]):
            sensordata[w, i] = 0.0
    if held.shape[0] > 0 and held[w]:  # an episode's fresh frame stays at its fresh state
        set_state(w, at, time, qpos, qvel, act, warmstart)


@wp.kernel
def _state_frame(t: wp.array(dtype=wp.int64), every: int, time: wp.array(dtype=wp.float32),
                 qpos: wp.array2d(dtype=wp.float32), qvel: wp.array2d(dtype=wp.float32),
                 act: wp.array2d(dtype=wp.float32), state: wp.array3d(dtype=wp.float32)):
    """Column j of the `state` frame of step t (time, qpos, qvel, act laid end to end)."""
    w, j = wp.tid()
    nq, nv = qpos.shape[1], qvel.shape[1]
    frame = int(t[0] // wp.int64(every))
    if j == 0:
        state[w, frame, 0] = time[w]
    elif j < 1 + nq:
        state[w, frame, j] = qpos[w, j - 1]
    elif j < 1 + nq + nv:
        state[w, frame, j] = qvel[w, j - 1 - nq]
    else:
        state[w, frame, j] = act[w, j - 1 - nq - nv]


@wp.kernel
def _columns(t: wp.array(dtype=wp.int64), every: int, source: wp.array2d(dtype=wp.float32),
             start: int, frames: wp.array3d(dtype=wp.float32)):
    """frames[w, t // every, j] = source[w, start + j]."""
    w, j = wp.tid()
    frames[w, int(t[0] // wp.int64(every)), j] = source[w, start + j]


def _warp(x: torch.Tensor) -> Any:
    return wp.from_torch(x)


def _empty(shape: tuple, dtype: torch.dtype, device: torch.device) -> Any:
    return wp.from_torch(torch.empty(shape, dtype=dtype, device=device))


class Inputs:
    """Step t's rows into MuJoCo Warp's input arrays, one launch per array.

    Args:
      rows: the driver's (nbatch, nstep, ncontrol) float32 rows, step t's read at every step.
      inputs: (columns of a control row, the array's (nbatch, width) torch view, boolean).
      episodes: the engine's `Episodes` (its `held` worlds take `reset_control`), or None.
    """

    def __init__(self, rows: torch.Tensor, inputs: list, episodes: Optional[Any]):
        device = rows.device
        self.rows = _warp(rows)
        if episodes is not None:
            self.held, self.reset = _warp(episodes.held), _warp(episodes.reset_control)
        else:
            self.held = _empty((0,), torch.bool, device)
            self.reset = _empty((0, 0), torch.float32, device)
        self.launches = [(_inputs_bool if boolean else _inputs, columns.start, _warp(view))
                         for columns, view, boolean in inputs if view.shape[1]]

    def launch(self, t: Any) -> None:
        """Before step `t` (its (1,) int64 Warp array)."""
        for kernel, start, target in self.launches:
            wp.launch(kernel, dim=target.shape, inputs=[t, self.rows, start, self.held,
                                                        self.reset, target])


class AfterStep:
    """The divergence check and restart, the episodes' hold and the frames of the records
    that are runs of columns, after each step.

    Args:
      views: the engine's (nbatch, -1) torch views of MuJoCo Warp's data arrays.
      qpos0: the model's qpos0, (1 or nbatch, nq).
      diverged: (nbatch,) bool, the batch's divergence flags (set, never cleared, here).
      episodes: the engine's `Episodes`, or None.
      records: {key: (record, frames)}: the engine's non-rendered records and their
        (nbatch, nframes, ...) frames.
      every: `record_every`.

    Attributes:
      rest: the keys of the records left to torch (`observe.value`).
    """

    def __init__(self, views: dict, qpos0: torch.Tensor, diverged: torch.Tensor,
                 episodes: Optional[Any], records: dict, every: int):
        device = diverged.device
        self.every = every
        self.state_key = next((key for key, (o, frames) in records.items()
                               if isinstance(o, records_.State)
                               and frames.dtype == torch.float32), None)
        v = {name: _warp(views[name]) for name in (
            "qpos", "qvel", "act", "qacc", "qacc_warmstart", "sensordata")}
        v["time"] = _warp(views["time"].reshape(-1))
        n = diverged.shape[0]
        self.bad = _warp(torch.zeros(n, dtype=torch.bool, device=device))  # this step's
        self.diverged = _warp(diverged)
        self.check = [v[k] for k in ("time", "qpos", "qvel", "qacc", "act", "sensordata")]
        self.ncheck = sum(a.shape[1] if a.ndim == 2 else 1 for a in self.check)
        if episodes is not None:
            hold = [_warp(episodes.held), _warp(episodes.at)]
        else:
            hold = [_empty((0,), torch.bool, device), _empty((0, 0), torch.float32, device)]
        self.restart = [_warp(qpos0.reshape(qpos0.shape[0], -1)),
                        *(v[k] for k in ("time", "qpos", "qvel", "act", "qacc_warmstart",
                                         "sensordata")), self.bad, *hold]
        self.physics = [v[k] for k in ("time", "qpos", "qvel", "act")]
        self.state = (_warp(records[self.state_key][1]) if self.state_key is not None
                      else None)
        self.columns, self.rest = [], []
        for key, (o, frames) in records.items():
            if key == self.state_key:
                continue
            run = _column_run(o, views, frames)
            if run is None:
                self.rest.append(key)
            elif run[2]:  # a record of no column writes nothing
                self.columns.append(run)

    def launch(self, t: Any, then: Any = None) -> None:
        """After step `t` (its (1,) int64 Warp array). `then`, called between the world's
        restart and hold and the frames of the column records: what brings the data to the
        frame's state (`record_kinematics="frame"`)."""
        n = self.diverged.shape[0]
        # one thread per world and value, as torch's copies are: one thread per world,
        # looping over a humanoid's 150 columns in sequence, cost about 33 microseconds a
        # step on an H200 at 4096 and 8192 worlds alike (the continued stream 0.966x raw
        # MuJoCo Warp before, 0.982x after; the suite's `warp-continued`)
        wp.launch(_check, dim=(n, self.ncheck), inputs=[*self.check, self.bad,
                                                        self.diverged])
        wp.launch(_restart, dim=n, inputs=self.restart)
        if self.state is not None:
            wp.launch(_state_frame, dim=(n, self.state.shape[2]),
                      inputs=[t, self.every, *self.physics, self.state])
        if then is not None:
            then()
        for source, start, width, frames in self.columns:
            wp.launch(_columns, dim=(n, width), inputs=[t, self.every, source, start, frames])


def _column_run(o: Any, views: dict, frames: torch.Tensor) -> Optional[tuple]:
    """(source array, first column, width, frames array) where record `o`'s value is a run
    of columns of one float32 data array (a field, a sensor, the centre of mass), else None."""
    if len(o.fields()) != 1 or frames.dtype != torch.float32:
        return None
    source = views[o.fields()[0]]
    if source.dtype != torch.float32 or not source.is_contiguous():
        return None
    value = warp_observe.value(o, views)
    n = source.shape[0]
    try:
        flat = value.view(n, -1)
    except RuntimeError:  # not a view of rows of the array
        return None
    if flat.untyped_storage().data_ptr() != source.untyped_storage().data_ptr() \
            or flat.stride(0) != source.stride(0) or (flat.shape[1] > 1 and flat.stride(1) != 1):
        return None
    start = (flat.data_ptr() - source.data_ptr()) // source.element_size()
    return _warp(source), int(start), int(flat.shape[1]), _warp(frames.view(n, frames.shape[1], -1))
