"""What a batch records (`record=`): one `Record` per name, written once for every engine.

A record knows its batch key, its per-frame shape and dtype, the `MjData` fields it is made of
(`made_of`: each with the shape MuJoCo C gives it) and its one default reading, `read`: its
value out of those fields, written over the array module (NumPy, `jax.numpy` or torch), as the
control generators are written over `draws.py`'s `Draws`. Every engine reads every kind
through it: the CPU engine from the buffers `mujoco.batch` records (`source`, `select`), MJX
(`backends/mjx/observe.py`) and MuJoCo Warp (`backends/warp/observe.py`) from the fields as
their data hold them (`value`). An engine overrides a kind only where its data differ, in its
own small table (`READINGS`, looked up by `override`). A new kind is a class here with its
`make` and `read`, and a line in `NAMED` or `PREFIXED`.

The kinds of names:

- `"state"`: `State`, the `mjSTATE_FULLPHYSICS` vector.
- `"qpos"`, `"xpos"`, ...: `Field`, an `MjData` field (a state component or anything `mj_step`
  computes), with the field's own trailing shape and dtype.
- `"sensor:NAME"`: `Sensor`, one sensor's columns of `sensordata`.
- `"com"`: `CentreOfMass`, the whole model's centre of mass, world coordinates.
- `Camera(...)`: one `CameraImage` per image, a camera's RGB, depth and segmentation images,
  each its own batch key (`"camera/NAME/rgb"`, ...). These are rendered, not read from fields
  (`Record.rendered`).

`simloader.observe` is this module under its former name; `Observation` is `Record`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any, Optional, Union

import mujoco
import numpy as np
from mujoco import batch as mj_batch

from simloader import layout

DEFAULT = ("state", "sensordata")
SENSOR_PREFIX = "sensor:"

# MjData fields mujoco.batch can record that hold no values of the simulation: plugin
# instance ids and pointers
_NOT_VALUES = {"plugin": "plugin instance ids", "plugin_data": "pointers to plugin data"}
# fields MuJoCo computes only when a sensor needs them (mj_rnePostConstraint, mj_subtreeVel),
# with what makes it compute them, for the error message; MJX follows the same rule
_ACC_SENSORS = ("only when the model has an accelerometer, force, torque, framelinacc or "
                "frameangacc sensor (mj_rnePostConstraint)")
_SUBTREE_SENSORS = "only when the model has a subtreelinvel or subtreeangmom sensor (mj_subtreeVel)"
_LAZY = {
    "cacc": _ACC_SENSORS, "cfrc_int": _ACC_SENSORS, "cfrc_ext": _ACC_SENSORS,
    "subtree_linvel": _SUBTREE_SENSORS, "subtree_angmom": _SUBTREE_SENSORS,
    "qfrc_inverse": "only in mj_inverse, which a step never calls",
}
F64 = np.dtype(np.float64)

# `record_kinematics=`: "before_step" (default): the derived fields as `mj_step` leaves them,
# those of the state before the step; "frame": what `mj_forward` computes at the frame's own
# state (its inputs and warmstart as the step left them)
KINEMATICS = ("before_step", "frame")
# the MjData fields computed in the acceleration stage (mj_fwdActuation, mj_fwdAcceleration,
# mj_fwdConstraint, mj_rnePostConstraint): the frame's value of one of these needs a whole
# mj_forward; every other derived field needs the position and velocity stages only
# (tests/test_record_kinematics.py checks every recordable field against mj_forward)
ACC_FIELDS = frozenset({
    "actuator_force", "qfrc_actuator", "act_dot", "qfrc_smooth", "qacc_smooth",
    "qfrc_constraint", "qacc", "efc_force", "efc_state", "efc_b", "cacc", "cfrc_int",
    "cfrc_ext", "solver", "solver_niter", "solver_nnz", "solver_fwdinv", "qfrc_inverse"})
# the implicit-damping factor the integrator computes after mj_forward: it belongs to the step
# that made the frame in either mode (mj_forward does not compute it)
INTEGRATOR_FIELDS = frozenset({"qH", "qHDiagInv"})

Shape = tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class Record:
    """One recorded output.

    Attributes:
      key: the batch key (the name as given in `record`).
      shape: the trailing shape of one frame (a batch holds `(nbatch, nframes, *shape)`).
      dtype: the dtype MuJoCo stores it in (float64 for mjtNum; int32 and bool stay so).
      made_of: the MjData fields its value is read from, each `(name, shape in MuJoCo C)`
        (a scalar field, such as time or ncon: `()`).
    """

    key: str
    shape: Shape
    dtype: np.dtype
    made_of: tuple[tuple[str, Shape], ...] = ()

    @property
    def floating(self) -> bool:
        """Whether `dtype=` applies to it (and the divergence check covers it)."""
        return self.dtype.kind == "f"

    @property
    def rendered(self) -> bool:
        """Whether it is an image rendered from the simulation's state rather than a value
        the simulation computes (a `CameraImage`)."""
        return False

    def fields(self) -> tuple[str, ...]:
        """The MjData fields its value is made of."""
        return tuple(name for name, _ in self.made_of)

    def read(self, xp: Any, fields: Mapping[str, Any]) -> Any:
        """The default reading: the value `(..., *shape)` from `fields`, `{name: (...,
        *MuJoCo's shape)}` with the same leading axes, over array module `xp` (numpy,
        jax.numpy or torch: the operations all three share). A view where it can be."""
        (name, _), = self.made_of
        return fields[name]

    def value(self, xp: Any, held: Mapping[str, Any], lead: Shape) -> Any:
        """The value `(*lead, *shape)` from the fields as an engine holds them, `held`
        (`{name: array}` of each field in `fields()`, `lead` leading axes, then the field's
        values in MuJoCo's row-major order in any shape: MJX's rotation matrices are
        `(n, 3, 3)` where MuJoCo's are `(n, 9)`)."""
        return self.read(xp, {name: held[name].reshape((*lead, *shape))
                              for name, shape in self.made_of})

    @property
    def buffer(self) -> tuple[Any, int]:
        """(what it is kept in, values a frame): records made of the same fields share one
        buffer (`sensor:NAME` and `sensordata`), one rendered or made of nothing has its own;
        for `memory.py`, which counts each buffer once. Each engine holds its buffers its own
        way (the CPU engine: `backends/cpu/recorded.py`)."""
        if self.rendered or not self.made_of:
            return self.key, math.prod(self.shape)
        return self.made_of, max(math.prod(self.shape),
                                 sum(math.prod(shape) for _, shape in self.made_of))


def override(record: Record, table: Mapping[type, Any]) -> Any:
    """An engine's override of `record`'s kind in `table` ({kind: reading}; a kind's
    subclasses included), or None: the default reading."""
    return next((table[kind] for kind in type(record).__mro__ if kind in table), None)


Observation = Record  # the former name


@dataclasses.dataclass(frozen=True)
class State(Record):
    """`"state"`: the mjSTATE_FULLPHYSICS state vector."""

    def read(self, xp, fields):
        time, *rest = (fields[name] for name in self.fields())
        return xp.concatenate([time[..., None], *rest], axis=-1)

    @classmethod
    def make(cls, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> State:
        nstate = (mujoco.mj_stateSize(model, layout.FULLPHYSICS),)
        return cls(name, nstate, F64, (("time", ()), ("qpos", (model.nq,)),
                                       ("qvel", (model.nv,)), ("act", (model.na,))))


@dataclasses.dataclass(frozen=True)
class Field(Record):
    """An MjData field, by its name."""

    @classmethod
    def make(cls, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> Field:
        if name in _NOT_VALUES:
            raise ValueError(f"record: {name} holds {_NOT_VALUES[name]}, not values of the "
                             f"simulation")
        if name == "time":
            return cls(name, (), F64, ((name, ()),))
        if name not in mj_batch.DATA_FIELDS:
            raise ValueError(f"record: {_unknown(model, data, name)}")
        value = getattr(data, name)
        if not isinstance(value, np.ndarray):  # counts (ncon, nefc, ...): int32 per step
            return cls(name, (), np.dtype(np.int32), ((name, ()),))
        return cls(name, value.shape, value.dtype, ((name, value.shape),))


@dataclasses.dataclass(frozen=True)
class Sensor(Record):
    """`"sensor:NAME"`: one sensor's columns `columns` of sensordata."""

    columns: tuple[int, int] = (0, 0)

    def read(self, xp, fields):
        return fields["sensordata"][..., self.columns[0]:self.columns[1]]

    @classmethod
    def make(cls, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> Sensor:
        sensor = name[len(SENSOR_PREFIX):]
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor)
        if i < 0:
            names = [n for n in valid_names(model) if n.startswith(SENSOR_PREFIX)]
            hint = layout.did_you_mean(name, names)
            raise ValueError(f"record: the model has no sensor {sensor!r}{hint}; its sensors: "
                             f"{names or '(none)'}")
        adr, dim = int(model.sensor_adr[i]), int(model.sensor_dim[i])
        return cls(name, (dim,), F64, (("sensordata", (model.nsensordata,)),),
                   (adr, adr + dim))


@dataclasses.dataclass(frozen=True)
class CentreOfMass(Record):
    """`"com"`: the centre of mass of the whole model in world coordinates, `(3,)`: the world
    body's row of `subtree_com` (as `mj_step` leaves it: the positions the step started
    from)."""

    def read(self, xp, fields):
        return fields["subtree_com"][..., 0, :]

    @classmethod
    def make(cls, model: mujoco.MjModel, data: mujoco.MjData, name: str) -> CentreOfMass:
        return cls(name, (3,), F64, (("subtree_com", (model.nbody, 3)),))


# the kinds by their name ("state") or prefix ("sensor:"); any other name is an MjData `Field`
NAMED: dict[str, type] = {"state": State, "com": CentreOfMass}
PREFIXED: dict[str, type] = {SENSOR_PREFIX: Sensor}


CAMERA_PREFIX = "camera/"
FREE = "free"  # the free camera's name (-1), in `Camera` and in the batch keys
# what a Camera delivers: batch key suffix -> (dtype, channels or None)
IMAGE_KINDS = {"rgb": (np.dtype(np.uint8), 3), "depth": (np.dtype(np.float32), None),
               "segmentation": (np.dtype(np.int32), None)}


@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera to render in every recorded frame, for `record=`.

    Args:
      camera: the camera's name or id in the model; "free" or -1 is the free camera
        (MuJoCo's default view). A camera of the model named "free" wins over the free
        camera: `Camera("free")` is that camera, `Camera(-1)` the free one.
      height, width: the image size in pixels.
      rgb: deliver `"camera/NAME/rgb"`, uint8 `(nbatch, nframes, height, width, 3)`.
      depth: deliver `"camera/NAME/depth"`, float32 metres from the camera,
        `(nbatch, nframes, height, width)`.
      segmentation: deliver `"camera/NAME/segmentation"`, int32 geom ids, -1 where no geom
        is seen, `(nbatch, nframes, height, width)`.
      shadows, multisample: the CPU renderer's (OpenGL) shadow maps and multisampling, on by
        default as `mujoco.Renderer` draws them. Off, software OpenGL on a machine without
        a GPU renders a scene with large shadow maps many times faster (MuJoCo Menagerie's
        scenes ask for 4096-pixel ones). MuJoCo Warp's ray tracer draws neither.

    NAME is the camera's name; an unnamed camera is named by its id, the free camera "free".
    """

    camera: Union[str, int]
    height: int = 64
    width: int = 64
    rgb: bool = True
    depth: bool = False
    segmentation: bool = False
    shadows: bool = True
    multisample: bool = True

    def __post_init__(self):
        if isinstance(self.camera, bool) or not isinstance(self.camera, (str, int, np.integer)):
            raise TypeError(f"Camera: camera must be a camera name (str) or id (int); \"free\" "
                            f"or -1 is the free camera; got {type(self.camera).__name__} "
                            f"{self.camera!r}")
        for name in ("height", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"Camera: {name} must be a positive int (pixels), got "
                                 f"{value!r}")
        for name in (*IMAGE_KINDS, "shadows", "multisample"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"Camera: {name} must be a bool, got "
                                f"{getattr(self, name)!r}")
        if not (self.rgb or self.depth or self.segmentation):
            raise ValueError(f"Camera: at least one of rgb, depth and segmentation must be True, "
                             f"got {self!r}")

    @property
    def kinds(self) -> tuple[str, ...]:
        """The images asked for, in the order "rgb", "depth", "segmentation"."""
        return tuple(k for k in IMAGE_KINDS if getattr(self, k))


@dataclasses.dataclass(frozen=True)
class CameraImage(Record):
    """One image of a `Camera`: `kind` ("rgb", "depth" or "segmentation") of camera
    `camera_id` (-1: the free camera), as asked by `camera`. Rendered from the poses, not
    read from MjData fields (`made_of` is empty)."""

    camera: Optional[Camera] = None
    camera_id: int = -1
    kind: str = "rgb"

    @property
    def floating(self) -> bool:
        # depth stays float32 metres whatever `dtype=` says, and far planes are not divergence
        return False

    @property
    def rendered(self) -> bool:
        return True


def camera_images(model: mujoco.MjModel, camera: Camera) -> tuple[CameraImage, ...]:
    """The records of `camera`, validated against the model.

    Raises:
      ValueError: an unknown camera name or an id out of range.
    """
    names = [layout.object_name(model, mujoco.mjtObj.mjOBJ_CAMERA, i, "camera")
             for i in range(model.ncam)]
    if isinstance(camera.camera, str):
        cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera.camera)
        # "free" is the free camera's name in the batch keys, unless a model camera has it
        if cam < 0 and camera.camera != FREE:
            raise ValueError(f"record: the model has no camera {camera.camera!r}"
                             f"{layout.did_you_mean(camera.camera, [*names, FREE])}; its "
                             f"cameras: {names or '(none)'}, or {FREE!r} (or -1) for the free "
                             f"camera")
    else:
        cam = int(camera.camera)
        if not -1 <= cam < model.ncam:
            raise ValueError(f"record: Camera(camera={cam}) is out of range: the model has "
                             f"{model.ncam} cameras (ids 0 to {model.ncam - 1}), and -1 is the "
                             f"free camera")
    name = FREE if cam < 0 else (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, cam)
                                   or str(cam))
    out = []
    for kind in camera.kinds:
        dtype, channels = IMAGE_KINDS[kind]
        shape = (camera.height, camera.width) + ((channels,) if channels else ())
        key = f"{CAMERA_PREFIX}{name}/{kind}"
        out.append(CameraImage(key, shape, dtype, (), camera, cam, kind))
    return tuple(out)


def frame_stage(model: mujoco.MjModel, records: Sequence[Record]) -> Optional[int]:
    """The forward stage (`mjtStage`) that makes every record of `records` describe the frame's
    own state (`record_kinematics="frame"`): mjSTAGE_VEL, or mjSTAGE_ACC where a record needs
    an acceleration-stage value (`ACC_FIELDS`, or a sensor MuJoCo computes there); None when
    the records are state components and images only, which need no forward at all."""
    stage = int(mujoco.mjtStage.mjSTAGE_NONE)
    vel, acc = int(mujoco.mjtStage.mjSTAGE_VEL), int(mujoco.mjtStage.mjSTAGE_ACC)
    for r in records:
        for name, _ in r.made_of:
            if name in layout.STATE_FIELDS or name in INTEGRATOR_FIELDS:
                continue
            if name == "sensordata":
                ids = (range(model.nsensor) if not isinstance(r, Sensor) else
                       [i for i in range(model.nsensor)
                        if model.sensor_adr[i] == r.columns[0]])
                need = max((int(model.sensor_needstage[i]) for i in ids), default=vel)
                stage = max(stage, vel, min(need, acc))
            else:
                stage = max(stage, acc if name in ACC_FIELDS else vel)
    return None if stage == int(mujoco.mjtStage.mjSTAGE_NONE) else stage


def recordable_fields() -> tuple[str, ...]:
    """The MjData field names `record` accepts (besides "state" and "sensor:NAME")."""
    return tuple(sorted(set(mj_batch.DATA_FIELDS) - set(_NOT_VALUES)))


def valid_names(model: mujoco.MjModel) -> list[str]:
    sensors = [SENSOR_PREFIX + layout.object_name(model, mujoco.mjtObj.mjOBJ_SENSOR, i, "sensor")
               for i in range(model.nsensor)]
    return ["state", *sensors, *recordable_fields(), *(n for n in NAMED if n != "state")]


def parse(model: mujoco.MjModel, record: Any) -> tuple[Record, ...]:
    """The records `record` names, validated against the model.

    Raises:
      TypeError: `record` is not a sequence of strings.
      ValueError: an unknown name (with the closest valid names and the list of all), a name
        given twice, a field that holds no per-step values, or one `mj_step` does not compute
        for this model.
    """
    if isinstance(record, (str, Camera)) or not isinstance(record, Sequence):
        raise TypeError(f"record: expected a sequence of names such as {DEFAULT} (and "
                        f"simloader.Camera), got {type(record).__name__} {record!r}")
    if not record:
        raise ValueError("record: expected at least one name, got an empty sequence")
    out, seen, data = [], set(), mujoco.MjData(model)
    for name in record:
        if isinstance(name, Camera):
            for image in camera_images(model, name):
                if image.key in seen:
                    raise ValueError(f"record: {image.key!r} is asked twice (two Cameras of "
                                     f"the same camera and image); give each camera once")
                seen.add(image.key)
                out.append(image)
            continue
        if not isinstance(name, str):
            raise TypeError(f"record: expected names (str) or simloader.Camera, got "
                            f"{type(name).__name__} {name!r}")
        if name in seen:
            raise ValueError(f"record: {name!r} is given twice")
        seen.add(name)
        out.append(_kind(name).make(model, data, name))
    _check_computed(model, data, out)
    return tuple(out)


def _kind(name: str) -> type:
    if name in NAMED:
        return NAMED[name]
    return next((kind for prefix, kind in PREFIXED.items() if name.startswith(prefix)), Field)


def _unknown(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> str:
    value = getattr(data, name, None)
    if value is not None and not isinstance(value, (np.ndarray, int, float)):
        return (f"{name} is a structured array whose size changes from step to step (one "
                f"{type(value).__name__} per step) and cannot be recorded; record 'ncon', "
                f"'cfrc_ext' or contact sensors instead")
    if isinstance(value, np.ndarray):
        return (f"{name} is in MjData's arena, whose size changes from step to step, and "
                f"cannot be recorded")
    hint = layout.did_you_mean(name, valid_names(model))
    named = ", ".join(repr(n) for n in NAMED if n != "state")
    return (f"unknown name {name!r}{hint}; valid names: 'state', 'sensordata', 'sensor:NAME' "
            f"for a sensor of the model, {named}, and the MjData fields "
            f"{', '.join(recordable_fields())}")


def _check_computed(model: mujoco.MjModel, data: mujoco.MjData,
                    records: Sequence[Record]) -> None:
    """Refuses floating fields `mj_step` leaves unset for this model: a step from the model's
    defaults must overwrite every value (probed with NaN)."""
    # state components hold the state; sensordata is the sensors' (user sensors without a
    # callback included: the contract's default record)
    unprobed = {*layout.STATE_FIELDS, "sensordata"}
    probed = list(dict.fromkeys(
        name for r in records for name, shape in r.made_of
        if name not in unprobed and math.prod(shape)
        and isinstance(value := getattr(data, name), np.ndarray) and value.dtype.kind == "f"))
    if not probed:
        return
    mujoco.mj_resetData(model, data)
    for name in probed:
        getattr(data, name)[...] = np.nan
    mujoco.mj_step(model, data)
    for name in probed:
        if np.isnan(getattr(data, name)).any():
            why = _LAZY.get(name, "for this model: its computation is off or absent here")
            raise ValueError(f"record: mj_step leaves {name} unset, so it would hold no values "
                             f"of the simulation: MuJoCo computes it {why}")
