"""Which columns of the state and control vectors mean what, by MuJoCo object name.

MuJoCo concatenates the components of an `mjtState` bitmask in the order of their bits
(`mj_getState`/`mj_setState`). This module computes that layout once per model so that the
rest of simloader (controls addressed by name, `simloader info`) never does index arithmetic.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Sequence
from typing import Optional

import mujoco
import numpy as np

S = mujoco.mjtState

# The components a control_spec may hold (mjSTATE_USER), in bit order, with the MuJoCo object
# kind each column group belongs to and the number of columns per object.
_USER_COMPONENTS = (
    # name, bit, object kind, columns per object
    ("ctrl", S.mjSTATE_CTRL, "actuator", 1),
    ("qfrc_applied", S.mjSTATE_QFRC_APPLIED, "dof", 1),
    ("xfrc_applied", S.mjSTATE_XFRC_APPLIED, "body", 6),
    ("eq_active", S.mjSTATE_EQ_ACTIVE, "equality", 1),
    ("mocap_pos", S.mjSTATE_MOCAP_POS, "mocap", 3),
    ("mocap_quat", S.mjSTATE_MOCAP_QUAT, "mocap", 4),
    ("userdata", S.mjSTATE_USERDATA, "userdata", 1),
)
# The components of mjSTATE_FULLPHYSICS, in bit order.
_PHYSICS_COMPONENTS = (
    ("time", S.mjSTATE_TIME),
    ("qpos", S.mjSTATE_QPOS),
    ("qvel", S.mjSTATE_QVEL),
    ("act", S.mjSTATE_ACT),
    ("history", S.mjSTATE_HISTORY),
    ("plugin_state", S.mjSTATE_PLUGIN),
    ("plastic", S.mjSTATE_PLASTIC),
)

USER = int(S.mjSTATE_USER)
FULLPHYSICS = int(S.mjSTATE_FULLPHYSICS)
INTEGRATION = int(S.mjSTATE_INTEGRATION)
COMPONENT_NAMES = tuple(c[0] for c in _USER_COMPONENTS)


def parse_control_spec(text: str) -> int:
    """A control_spec from its names, as `ctrl|xfrc_applied` (any case, spaces allowed), or
    an integer bitmask written in digits; the Python API and the command line share it.

    Raises:
      ValueError: an unknown component name.
    """
    if text.strip().isdigit():
        return int(text)
    spec = 0
    for part in text.split("|"):
        name = part.strip().lower()
        if name not in COMPONENT_NAMES:
            close = difflib.get_close_matches(name, COMPONENT_NAMES, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ValueError(f"control_spec: unknown component {part.strip()!r}{hint}; known: "
                             f"{list(COMPONENT_NAMES)}")
        spec |= int(next(bit for n, bit, _, _ in _USER_COMPONENTS if n == name))
    return spec


@dataclasses.dataclass(frozen=True)
class Component:
    """One component of a state or control vector.

    Attributes:
      name: MjData field name (`ctrl`, `xfrc_applied`, `qpos`, ...).
      bit: its `mjtState` bit.
      start: first column of the component in the vector.
      size: number of columns.
      width: columns per object (6 for `xfrc_applied`, 1 for `ctrl`, ...).
      objects: names of the objects the column groups belong to, `size // width` of them
        (unnamed objects are called `kind#index`).
    """

    name: str
    bit: int
    start: int
    size: int
    width: int
    objects: tuple[str, ...]

    @property
    def columns(self) -> slice:
        return slice(self.start, self.start + self.size)

    def object_columns(self, names) -> np.ndarray:
        """Columns (within the component) of the named objects, in the order given.

        Raises:
          ValueError: a name is not an object of this component.
        """
        cols = []
        for name in [names] if isinstance(names, str) else names:
            if name not in self.objects:
                close = difflib.get_close_matches(str(name), self.objects, n=3)
                hint = f" (did you mean {', '.join(map(repr, close))}?)" if close else ""
                raise ValueError(
                    f"on: {self.name} has no object {name!r}{hint}; its objects are "
                    f"{list(self.objects)}")
            i = self.objects.index(name)
            cols.extend(range(i * self.width, (i + 1) * self.width))
        return np.asarray(cols, dtype=np.intp)


def _name(model: mujoco.MjModel, objtype: mujoco.mjtObj, i: int, kind: str) -> str:
    return mujoco.mj_id2name(model, objtype, i) or f"{kind}#{i}"


def _objects(model: mujoco.MjModel, kind: str) -> tuple[str, ...]:
    O = mujoco.mjtObj
    if kind == "actuator":
        return tuple(_name(model, O.mjOBJ_ACTUATOR, i, kind) for i in range(model.nu))
    if kind == "body":
        return tuple(_name(model, O.mjOBJ_BODY, i, kind) for i in range(model.nbody))
    if kind == "equality":
        return tuple(_name(model, O.mjOBJ_EQUALITY, i, kind) for i in range(model.neq))
    if kind == "mocap":
        bodies = np.flatnonzero(model.body_mocapid >= 0)
        order = np.argsort(model.body_mocapid[bodies])
        return tuple(_name(model, O.mjOBJ_BODY, int(b), "body") for b in bodies[order])
    if kind == "dof":
        # a dof is named after its joint, with the axis index for multi-dof joints
        names = []
        for j in range(model.njnt):
            jname = _name(model, O.mjOBJ_JOINT, j, "joint")
            ndof = {0: 6, 1: 3}.get(int(model.jnt_type[j]), 1)
            names.extend([jname] if ndof == 1 else [f"{jname}[{k}]" for k in range(ndof)])
        return tuple(names)
    return tuple(f"userdata#{i}" for i in range(model.nuserdata))


def control_layout(model: mujoco.MjModel, control_spec: int) -> tuple[Component, ...]:
    """The components of the control vector selected by `control_spec`, in MuJoCo's order."""
    out, start = [], 0
    for name, bit, kind, width in _USER_COMPONENTS:
        if not control_spec & int(bit):
            continue
        size = mujoco.mj_stateSize(model, int(bit))
        out.append(Component(name, int(bit), start, size, width, _objects(model, kind)))
        start += size
    return tuple(out)


def state_layout(model: mujoco.MjModel) -> tuple[Component, ...]:
    """The components of the `mjSTATE_FULLPHYSICS` state vector, in MuJoCo's order."""
    out, start = [], 0
    O = mujoco.mjtObj
    for name, bit in _PHYSICS_COMPONENTS:
        size = mujoco.mj_stateSize(model, int(bit))
        if name in ("qpos", "qvel"):
            objects = _qpos_names(model) if name == "qpos" else _objects(model, "dof")
        elif name == "act":
            objects = tuple(_name(model, O.mjOBJ_ACTUATOR, int(i), "actuator")
                            for i in range(model.nu) for _ in range(int(model.actuator_actnum[i])))
        else:
            objects = tuple(f"{name}#{i}" for i in range(size))
        out.append(Component(name, int(bit), start, size, 1, objects))
        start += size
    return tuple(out)


def _qpos_names(model: mujoco.MjModel) -> tuple[str, ...]:
    names = []
    for j in range(model.njnt):
        jname = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint")
        nq = {0: 7, 1: 4}.get(int(model.jnt_type[j]), 1)
        names.extend([jname] if nq == 1 else [f"{jname}[{k}]" for k in range(nq)])
    return tuple(names)


def component_columns(model: mujoco.MjModel, outer: int, inner: int) -> np.ndarray:
    """Columns of the `inner` state vector within the `outer` one (inner's bits within outer's)."""
    cols, start = [], 0
    for k in range(int(S.mjNSTATE)):
        bit = 1 << k
        if not outer & bit:
            continue
        size = mujoco.mj_stateSize(model, bit)
        if inner & bit:
            cols.extend(range(start, start + size))
        start += size
    return np.asarray(cols, dtype=np.intp)


def reset_state(model: mujoco.MjModel, spec: int) -> np.ndarray:
    """The `spec` state vector `mj_resetData` leaves: for user inputs zero forces and
    controls, mocap bodies at their model poses, equalities at `eq_active0` (what an undriven
    control column holds); for mjSTATE_INTEGRATION also a zero warmstart."""
    data = mujoco.MjData(model)
    row = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, row, spec)
    return row


def reset_rows(models: Sequence[mujoco.MjModel], spec: int) -> np.ndarray:
    """(len(models), size of spec): `reset_state` of each model (model lists, variants)."""
    return np.stack([reset_state(m, spec) for m in models])


def describe(model: mujoco.MjModel, control_spec: int = int(S.mjSTATE_CTRL),
             source: Optional[str] = None) -> str:
    """A human-readable table of the state and control columns, by object name (after where
    the model comes from, when `source` says)."""
    lines = [f"model: {source}"] if source else []
    lines.append(f"state (mjSTATE_FULLPHYSICS), nstate = {mujoco.mj_stateSize(model, FULLPHYSICS)}")
    for c in state_layout(model):
        if c.size:
            lines.append(f"  [{c.start}:{c.start + c.size}] {c.name}: {', '.join(c.objects)}")
    lines.append(f"control (control_spec = {control_spec}), ncontrol = "
                 f"{mujoco.mj_stateSize(model, control_spec)}")
    for c in control_layout(model, control_spec):
        lines.append(f"  [{c.start}:{c.start + c.size}] {c.name} ({c.width} per object): "
                     f"{', '.join(c.objects) if c.objects else '(none)'}")
    lines.append(f"sensordata, nsensordata = {model.nsensordata}")
    for i in range(model.nsensor):
        adr, dim = int(model.sensor_adr[i]), int(model.sensor_dim[i])
        lines.append(f"  [{adr}:{adr + dim}] "
                     f"{_name(model, mujoco.mjtObj.mjOBJ_SENSOR, i, 'sensor')}")
    return "\n".join(lines)
