"""Which columns of the state and control vectors mean what, by MuJoCo object name.

MuJoCo concatenates the components of an `mjtState` bitmask in the order of their bits
(`mj_getState`/`mj_setState`). This module computes that layout once per model so that the
rest of simloader (controls addressed by name, `simloader info`) never does index arithmetic.
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Sequence
from typing import Any, Optional

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
# MjData fields that are components of the state (mjtState), each set by mj_setState
STATE_FIELDS = (*(c[0] for c in _PHYSICS_COMPONENTS), "qacc_warmstart",
                *(c[0] for c in _USER_COMPONENTS))

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
            hint = did_you_mean(name, COMPONENT_NAMES)
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
                raise ValueError(
                    f"on: {self.name} has no object {name!r}{did_you_mean(name, self.objects)}; "
                    f"its objects are "
                    f"{list(self.objects)}")
            i = self.objects.index(name)
            cols.extend(range(i * self.width, (i + 1) * self.width))
        return np.asarray(cols, dtype=np.intp)


def object_name(model: mujoco.MjModel, objtype: mujoco.mjtObj, i: int, kind: str) -> str:
    return mujoco.mj_id2name(model, objtype, i) or f"{kind}#{i}"


def _objects(model: mujoco.MjModel, kind: str) -> tuple[str, ...]:
    O = mujoco.mjtObj
    if kind == "actuator":
        return tuple(object_name(model, O.mjOBJ_ACTUATOR, i, kind) for i in range(model.nu))
    if kind == "body":
        return tuple(object_name(model, O.mjOBJ_BODY, i, kind) for i in range(model.nbody))
    if kind == "equality":
        return tuple(object_name(model, O.mjOBJ_EQUALITY, i, kind) for i in range(model.neq))
    if kind == "mocap":
        bodies = np.flatnonzero(model.body_mocapid >= 0)
        order = np.argsort(model.body_mocapid[bodies])
        return tuple(object_name(model, O.mjOBJ_BODY, int(b), "body") for b in bodies[order])
    if kind == "dof":
        # a dof is named after its joint, with the axis index for multi-dof joints
        names = []
        for j in range(model.njnt):
            jname = object_name(model, O.mjOBJ_JOINT, j, "joint")
            ndof = {0: 6, 1: 3}.get(int(model.jnt_type[j]), 1)
            names.extend([jname] if ndof == 1 else [f"{jname}[{k}]" for k in range(ndof)])
        return tuple(names)
    if kind in _NAMED_KINDS:
        count, objtype = _NAMED_KINDS[kind]
        return tuple(object_name(model, objtype, i, kind) for i in range(getattr(model, count)))
    return tuple(f"userdata#{i}" for i in range(model.nuserdata))


# object kinds named by mj_id2name, beyond those above: kind -> (MjModel count, mjtObj)
_NAMED_KINDS = {
    "geom": ("ngeom", mujoco.mjtObj.mjOBJ_GEOM),
    "joint": ("njnt", mujoco.mjtObj.mjOBJ_JOINT),
    "site": ("nsite", mujoco.mjtObj.mjOBJ_SITE),
    "tendon": ("ntendon", mujoco.mjtObj.mjOBJ_TENDON),
    "pair": ("npair", mujoco.mjtObj.mjOBJ_PAIR),
    "sensor": ("nsensor", mujoco.mjtObj.mjOBJ_SENSOR),
    "camera": ("ncam", mujoco.mjtObj.mjOBJ_CAMERA),
    "light": ("nlight", mujoco.mjtObj.mjOBJ_LIGHT),
    "material": ("nmat", mujoco.mjtObj.mjOBJ_MATERIAL),
    "mesh": ("nmesh", mujoco.mjtObj.mjOBJ_MESH),
    "hfield": ("nhfield", mujoco.mjtObj.mjOBJ_HFIELD),
    "texture": ("ntex", mujoco.mjtObj.mjOBJ_TEXTURE),
    "flex": ("nflex", mujoco.mjtObj.mjOBJ_FLEX),
    "skin": ("nskin", mujoco.mjtObj.mjOBJ_SKIN),
    "numeric": ("nnumeric", mujoco.mjtObj.mjOBJ_NUMERIC),
    "key": ("nkey", mujoco.mjtObj.mjOBJ_KEY),
}
# MjModel field prefix -> the kind of object each row of the field belongs to (a field whose
# row count is not that kind's count, as mesh_vert, has rows of no object)
_FIELD_KINDS = (("body_", "body"), ("geom_", "geom"), ("jnt_", "joint"), ("dof_", "dof"),
                ("actuator_", "actuator"), ("tendon_", "tendon"), ("site_", "site"),
                ("eq_", "equality"), ("pair_", "pair"), ("sensor_", "sensor"),
                ("cam_", "camera"), ("light_", "light"), ("mat_", "material"),
                ("mesh_", "mesh"), ("hfield_", "hfield"), ("tex_", "texture"),
                ("flex_", "flex"), ("skin_", "skin"), ("numeric_", "numeric"), ("key_", "key"))


def param_columns(model: mujoco.MjModel, field: str, rows: Sequence[int], cols: Sequence[int],
                  width: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Names of the values of a randomized MjModel field (`rows` x `cols` of the field seen as
    rows of `width` values; `opt.*`: one row), as the state and control columns are named:
    (the object of each value, the name of each value). An object is named as in
    `state_layout` (a body, geom, joint, actuator, ...; a dof after its joint, with the axis
    for multi-dof joints; `opt.*` after the option); a field of several values per object
    adds the component, `floor[0]` for geom_friction's sliding friction of geom floor."""
    kind = next((k for prefix, k in _FIELD_KINDS if field.startswith(prefix)), None)
    names = _objects(model, kind) if kind is not None else ()
    rows = [int(r) for r in rows]
    if field.startswith("opt."):
        row_names = [field] * len(rows)
    elif rows and len(names) > max(rows) and len(names) == getattr(model, field).shape[0]:
        row_names = [names[r] for r in rows]
    else:  # rows of no named object
        row_names = [f"{field}#{r}" for r in rows]
    objects = tuple(o for o in row_names for _ in cols)
    if width == 1:
        return objects, objects
    return objects, tuple(f"{o}[{int(c)}]" for o in row_names for c in cols)


def describe_params(params: dict[str, tuple[tuple[str, ...], tuple[str, ...]]],
                    nbatch: Any = "nbatch") -> str:
    """One line per `batch["params"]` key: its shape and the name of each column."""
    return "\n".join(f"  {key} ({nbatch}, {len(columns)}): columns {', '.join(columns)}"
                     for key, (_, columns) in params.items())


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
            objects = tuple(object_name(model, O.mjOBJ_ACTUATOR, int(i), "actuator")
                            for i in range(model.nu) for _ in range(int(model.actuator_actnum[i])))
        else:
            objects = tuple(f"{name}#{i}" for i in range(size))
        out.append(Component(name, int(bit), start, size, 1, objects))
        start += size
    return tuple(out)


def _qpos_names(model: mujoco.MjModel) -> tuple[str, ...]:
    names = []
    for j in range(model.njnt):
        jname = object_name(model, mujoco.mjtObj.mjOBJ_JOINT, j, "joint")
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
                     f"{object_name(model, mujoco.mjtObj.mjOBJ_SENSOR, i, 'sensor')}")
    return "\n".join(lines)


# MjData's named views (data.body(i), ...), whose attributes are slices of MjData fields
_VIEW_KINDS = (("body", "nbody", mujoco.mjtObj.mjOBJ_BODY),
               ("joint", "njnt", mujoco.mjtObj.mjOBJ_JOINT),
               ("actuator", "nu", mujoco.mjtObj.mjOBJ_ACTUATOR),
               ("geom", "ngeom", mujoco.mjtObj.mjOBJ_GEOM),
               ("site", "nsite", mujoco.mjtObj.mjOBJ_SITE),
               ("sensor", "nsensor", mujoco.mjtObj.mjOBJ_SENSOR),
               ("tendon", "ntendon", mujoco.mjtObj.mjOBJ_TENDON),
               ("camera", "ncam", mujoco.mjtObj.mjOBJ_CAMERA),
               ("light", "nlight", mujoco.mjtObj.mjOBJ_LIGHT))


@dataclasses.dataclass(frozen=True)
class Part:
    """Where a named part lies in a batch tensor.

    Attributes:
      key: the batch key holding it.
      start, stop: its range of the key's trailing values, flattened.
      shape: its own trailing shape.
    """

    key: str
    start: int
    stop: int
    shape: tuple[int, ...]


def _field_objects(model: mujoco.MjModel, data: mujoco.MjData,
                   field: str) -> dict[str, tuple[int, int, tuple[int, ...]]]:
    """{object name: (start, stop, shape)} of MjData field `field`'s flattened values, from
    MjData's named views (`data.body("hand").xpos` is a slice of `data.xpos`)."""
    full = getattr(data, field, None)
    if not isinstance(full, np.ndarray) or not full.size:
        return {}
    lo, hi = full.ctypes.data, full.ctypes.data + full.nbytes
    out: dict[str, tuple[int, int, tuple[int, ...]]] = {}
    for kind, count, objtype in _VIEW_KINDS:
        n = getattr(model, count)
        if not n:
            continue
        first = getattr(data, kind)(0)
        attrs = [a for a in dir(first) if not a.startswith("_")
                 and isinstance(part := getattr(first, a), np.ndarray) and part.dtype == full.dtype
                 and part.size and lo <= part.ctypes.data < hi]
        for attr in attrs[:1]:
            for i in range(n):
                part = getattr(getattr(data, kind)(i), attr)
                if not part.size:
                    continue
                start = (part.ctypes.data - lo) // full.itemsize
                out.setdefault(object_name(model, objtype, i, kind),
                               (start, start + part.size, part.shape))
    return out


PARAMS = "params/"  # the layout's key of batch["params"][KEY], as a store names it


class BatchLayout:
    """What each column of a batch means, by name: `locate(name, obj)` finds a part of a
    batch key (a state component of `state`, a control component of `control`, a sensor of
    `sensordata`, an object's rows of a recorded field) as a range of its trailing values.

    Plain data (picklable, small): built once per dataset from the model, the control spec and
    the recorded observations.
    """

    def __init__(self, model: mujoco.MjModel, control_spec: int, observations: Sequence[Any],
                 params: Optional[dict[str, tuple[tuple[str, ...], tuple[str, ...]]]] = None):
        data = mujoco.MjData(model)
        self.keys = {o.key: tuple(o.shape) for o in observations}
        self.keys["control"] = (mujoco.mj_stateSize(model, control_spec),)
        self.keys["initial_state"] = (mujoco.mj_stateSize(model, FULLPHYSICS),)
        # MjData field shapes (time: a scalar)
        self.field_shapes = {"time": ()}
        # where a field lies within a concatenated key: {field: {key: (start, stop)}}
        self.within: dict[str, dict[str, tuple[int, int]]] = {}
        components = [(c, k) for c in state_layout(model) for k in ("state", "initial_state")]
        components += [(c, "control") for c in control_layout(model, control_spec)]
        sensors = {}
        for i in range(model.nsensor):
            adr, dim = int(model.sensor_adr[i]), int(model.sensor_dim[i])
            sensors["sensor:" + object_name(model, mujoco.mjtObj.mjOBJ_SENSOR, i, "sensor")] = (
                adr, adr + dim)
        for c, key in components:
            if key in self.keys and c.size:
                self.within.setdefault(c.name, {})[key] = (c.start, c.start + c.size)
        if "sensordata" in self.keys:
            for name, cols in sensors.items():
                self.within.setdefault(name, {})["sensordata"] = cols
        fields = set(self.within) | set(self.keys)
        for field in fields:
            value = getattr(data, field, None)
            if isinstance(value, np.ndarray):
                self.field_shapes[field] = value.shape
            elif field in sensors:
                self.field_shapes[field] = (sensors[field][1] - sensors[field][0],)
        # objects along each field: {field: {object: (start, stop, shape)}}
        self.objects = {f: _field_objects(model, data, f) for f in sorted(fields)
                        if f in self.field_shapes}
        self.objects["sensordata"] = {n[len("sensor:"):]: (a, b, (b - a,))
                                      for n, (a, b) in sensors.items()}
        self.objects = {f: o for f, o in self.objects.items() if o}
        # randomized parameters (`params`: {key: (object, name) of each column}, from
        # `param_columns`), held in batch["params"][key]: key "params/KEY", one part per
        # object (its columns) and per component column ("floor[0]")
        self.params = dict(params or {})
        for key, (objects, columns) in self.params.items():
            parts: dict[str, tuple[int, int, tuple[int, ...]]] = {}
            for i, (obj, column) in enumerate(zip(objects, columns)):
                parts[column] = (i, i + 1, (1,))
                if column != obj:  # a component: its object's part spans its columns
                    a, b, _ = parts.get(obj, (i, i, ()))
                    if b == i:
                        parts[obj] = (a, i + 1, (i + 1 - a,))
            self.keys[PARAMS + key] = (len(columns),)
            self.objects[PARAMS + key] = parts

    def locate(self, name: str, obj: Optional[str] = None, of: Optional[str] = None) -> Part:
        """The part `name` (a batch key, a state or control component, "sensor:NAME"), or
        object `obj`'s part of it, in batch key `of` (default: `name`'s own key if recorded,
        else the key that holds it).

        Raises:
          KeyError: the batch holds no such part (with the names it holds).
        """
        if of is None and name not in self.keys and PARAMS + name in self.keys:
            name = PARAMS + name  # a batch["params"] key, by its own name
        if of is None:
            of = name if name in self.keys else next(iter(self.within.get(name, {})), None)
        if of is None or of not in self.keys:
            held = sorted(set(self.keys) | set(self.within))
            raise KeyError(f"{name!r}{' in ' + repr(of) if of else ''}: the batch holds no such "
                           f"part{did_you_mean(name, held)}; it holds {held}")
        if of == name:
            start, stop, shape = 0, int(np.prod(self.keys[of])), self.keys[of]
        elif name in self.within and of in self.within[name]:
            (start, stop), shape = self.within[name][of], self.field_shapes[name]
        else:
            raise KeyError(f"{name!r} is not part of {of!r}; parts of {of!r}: "
                           f"{sorted(n for n, w in self.within.items() if of in w)}")
        if obj is None:
            return Part(of, start, stop, tuple(shape))
        objects = self.objects.get("sensordata" if name.startswith("sensor:") else name, {})
        if obj not in objects:
            raise KeyError(f"{name!r} has no object {obj!r}{did_you_mean(obj, objects)}; "
                           f"its objects: {list(objects) or '(none)'}")
        a, b, part_shape = objects[obj]
        return Part(of, start + a, start + b, tuple(part_shape))

    def describe(self) -> str:
        """One line per recorded key and the named parts it holds."""
        lines = []
        for key, shape in self.keys.items():
            if key in ("control", "initial_state") or key.startswith(PARAMS):
                continue  # params: `describe_params`
            parts = [n for n, w in self.within.items() if key in w]
            objects = list(self.objects.get(key, {}))
            what = (f"parts {', '.join(parts)}" if parts else
                    f"rows of {', '.join(objects)}" if objects else "")
            lines.append(f"  {key} {tuple(shape)}{': ' + what if what else ''}")
        return "\n".join(lines)


def did_you_mean(name: Any, names) -> str:
    """' (did you mean ...?)' with the names closest to `name`, or ''."""
    close = difflib.get_close_matches(str(name), list(names), n=3)
    return f" (did you mean {', '.join(map(repr, close))}?)" if close else ""
