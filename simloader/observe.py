"""What a batch records (`record=`): observations as data.

Each name of `record` becomes one `Observation` that knows its batch key, its per-frame shape
and dtype, what `mujoco.batch` records for it on the CPU (`source`, a field name or an
`mjtState` spec, and the part of that record it delivers) and, for MJX, its value computed from
one trajectory's `mjx.Model`/`mjx.Data` (`jax_value`). The CPU backend and delivery loop over
the observations; none of them names a key.

Kinds of names:
  "state"            `State`: the `mjSTATE_FULLPHYSICS` vector.
  "qpos", "xpos", .. `Field`: an `MjData` field (a state component or anything `mj_step`
                     computes), with the field's own trailing shape and dtype.
  "sensor:NAME"      `Sensor`: one sensor's columns of `sensordata`.
  Camera(...)        `CameraImage`s: a camera's RGB, depth and segmentation images, each its
                     own batch key ("camera/NAME/rgb", ...). These are rendered, not recorded
                     by `mujoco.batch` (`Observation.rendered`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
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
# the components of mjSTATE_FULLPHYSICS that MJX simulates (the others must be empty there)
_MJX_PHYSICS = int(mujoco.mjtState.mjSTATE_TIME | mujoco.mjtState.mjSTATE_QPOS
                   | mujoco.mjtState.mjSTATE_QVEL | mujoco.mjtState.mjSTATE_ACT)
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


@dataclasses.dataclass(frozen=True)
class Observation:
    """One recorded output.

    Attributes:
      key: the batch key (the name as given in `record`).
      shape: the trailing shape of one frame (a batch holds `(nbatch, nframes, *shape)`).
      dtype: the dtype MuJoCo stores it in (float64 for mjtNum; int32 and bool stay so).
      source: what `mujoco.batch.Batch.rollout` records for it: a field name or an mjtState
        spec. Observations with the same source share one recorded buffer.
      source_shape: the trailing shape of what is recorded for `source`.
      columns: the columns of the source's last axis this observation delivers, or None for
        all of them.
    """

    key: str
    shape: tuple[int, ...]
    dtype: np.dtype
    source: Union[str, int]
    source_shape: tuple[int, ...]
    columns: Optional[tuple[int, int]] = None

    @property
    def floating(self) -> bool:
        """Whether `dtype=` applies to it (and the divergence check covers it)."""
        return self.dtype.kind == "f"

    @property
    def rendered(self) -> bool:
        """Whether it is an image rendered from the simulation's state rather than a value
        the simulation computes (a `CameraImage`)."""
        return False

    def select(self, recorded: Any) -> Any:
        """This observation out of its source's recorded `(nbatch, nframes, *source_shape)`
        buffer (a NumPy array or torch tensor): a view, no copy."""
        if self.columns is not None:
            return recorded[..., self.columns[0]:self.columns[1]]
        return recorded.reshape(*recorded.shape[:2], *self.shape)

    def jax_value(self, m: Any, d: Any) -> Any:
        """The value of one frame, `shape`, from one trajectory's `mjx.Model` and `mjx.Data`
        (pure; called inside `vmap` inside the scan body). MJX's dtype (float32 unless JAX
        runs with x64; integer and bool fields keep theirs)."""
        raise NotImplementedError

    def mjx_refusal(self, data: Any) -> Optional[str]:
        """Why MJX (whose `make_data` gives `data`) cannot record this, or None."""
        return None

    def fields(self) -> tuple[str, ...]:
        """The MjData fields its value is made of."""
        return (self.key,)

    def torch_value(self, fields: dict[str, Any]) -> Any:
        """The value of one frame of a whole batch, `(nbatch, *shape)`, from torch tensors
        `(nbatch, ...)` of the MjData fields named by `fields()` (MuJoCo Warp's arrays, for
        the Warp closed loop): a view of them where the layout allows, else a new tensor."""
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class State(Observation):
    """`"state"`: the mjSTATE_FULLPHYSICS state vector."""

    def jax_value(self, m, d):
        from mujoco import mjx
        return mjx.get_state(m, d, _MJX_PHYSICS)

    def fields(self):
        return ("time", "qpos", "qvel", "act")

    def torch_value(self, fields):
        import torch
        time, *rest = (fields[name] for name in self.fields())
        return torch.cat([time.reshape(-1, 1), *rest], dim=1)


@dataclasses.dataclass(frozen=True)
class Field(Observation):
    """An MjData field, by its name."""

    def jax_value(self, m, d):
        # rotation matrices are (n, 3, 3) in MJX, (n, 9) in MuJoCo: the same values, row-major
        return _mjx_field(d, self.key).reshape(self.shape)

    def torch_value(self, fields):
        value = fields[self.key]
        return value.reshape(value.shape[0], *self.shape)

    def mjx_refusal(self, data):
        import jax
        value = _mjx_field(data, self.key)
        if value is None:
            return f"MJX has no field {self.key}"
        if not isinstance(value, jax.Array):
            return (f"MJX holds {self.key} as a constant of the compiled "
                    f"model (a size fixed at compilation), not per trajectory")
        if tuple(value.shape) != self.shape and not (
                self.key.endswith("mat") and value.size == math.prod(self.shape)):
            return (f"MJX stores {self.key} with shape {tuple(value.shape)}, "
                    f"MuJoCo with shape {self.shape} (another layout, e.g. dense instead of "
                    f"sparse)")
        if np.dtype(value.dtype).kind != self.dtype.kind:
            return f"MJX stores {self.key} as {value.dtype}, MuJoCo as {self.dtype}"
        return None


@dataclasses.dataclass(frozen=True)
class Sensor(Observation):
    """`"sensor:NAME"`: one sensor's columns of sensordata."""

    def jax_value(self, m, d):
        return d.sensordata[self.columns[0]:self.columns[1]]

    def fields(self):
        return ("sensordata",)

    def torch_value(self, fields):
        return fields["sensordata"][:, self.columns[0]:self.columns[1]]


CAMERA_PREFIX = "camera/"
# what a Camera delivers: batch key suffix -> (dtype, channels or None)
IMAGE_KINDS = {"rgb": (np.dtype(np.uint8), 3), "depth": (np.dtype(np.float32), None),
               "segmentation": (np.dtype(np.int32), None)}


@dataclasses.dataclass(frozen=True)
class Camera:
    """A camera to render in every recorded frame, for `record=`.

    Args:
      camera: the camera's name or id in the model; -1 is the free camera (MuJoCo's default
        view).
      height, width: the image size in pixels.
      rgb: deliver `"camera/NAME/rgb"`, uint8 `(nbatch, nframes, height, width, 3)`.
      depth: deliver `"camera/NAME/depth"`, float32 metres from the camera,
        `(nbatch, nframes, height, width)`.
      segmentation: deliver `"camera/NAME/segmentation"`, int32 geom ids, -1 where no geom
        is seen, `(nbatch, nframes, height, width)`.

    NAME is the camera's name; an unnamed camera is named by its id, the free camera "free".
    """

    camera: Union[str, int]
    height: int = 64
    width: int = 64
    rgb: bool = True
    depth: bool = False
    segmentation: bool = False

    def __post_init__(self):
        if isinstance(self.camera, bool) or not isinstance(self.camera, (str, int, np.integer)):
            raise TypeError(f"Camera: camera must be a camera name (str) or id (int, -1 for the "
                            f"free camera), got {type(self.camera).__name__} {self.camera!r}")
        for name in ("height", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"Camera: {name} must be a positive int (pixels), got "
                                 f"{value!r}")
        for name in IMAGE_KINDS:
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
class CameraImage(Observation):
    """One image of a `Camera`: `kind` ("rgb", "depth" or "segmentation") of camera
    `camera_id` (-1: the free camera), as asked by `camera`."""

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

    def select(self, recorded: Any) -> Any:
        return recorded

    def fields(self):
        return ()  # rendered from the poses, not read from an MjData field


def camera_images(model: mujoco.MjModel, camera: Camera) -> tuple[CameraImage, ...]:
    """The observations of `camera`, validated against the model.

    Raises:
      ValueError: an unknown camera name or an id out of range.
    """
    names = [layout.object_name(model, mujoco.mjtObj.mjOBJ_CAMERA, i, "camera")
             for i in range(model.ncam)]
    if isinstance(camera.camera, str):
        cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera.camera)
        if cam < 0:
            raise ValueError(f"record: the model has no camera {camera.camera!r}"
                             f"{layout.did_you_mean(camera.camera, names)}; its cameras: "
                             f"{names or '(none)'}, or -1 for the free camera")
    else:
        cam = int(camera.camera)
        if not -1 <= cam < model.ncam:
            raise ValueError(f"record: Camera(camera={cam}) is out of range: the model has "
                             f"{model.ncam} cameras (ids 0 to {model.ncam - 1}), and -1 is the "
                             f"free camera")
    name = "free" if cam < 0 else (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, cam)
                                   or str(cam))
    out = []
    for kind in camera.kinds:
        dtype, channels = IMAGE_KINDS[kind]
        shape = (camera.height, camera.width) + ((channels,) if channels else ())
        key = f"{CAMERA_PREFIX}{name}/{kind}"
        out.append(CameraImage(key, shape, dtype, key, shape, None, camera, cam, kind))
    return tuple(out)


def jax_frame(observations: Sequence[Observation], model_axes: Any, m: Any,
              d: Any) -> dict[str, Any]:
    """One frame of every observation, `{key: (nbatch, *shape)}`, from the batched `mjx.Data`
    `d` and its `mjx.Model` `m` (batched along `model_axes`); pure, for the scan body, whose
    stacked outputs are then `(nframes, nbatch, *shape)`."""
    import jax
    return jax.vmap(lambda m, d: {o.key: o.jax_value(m, d) for o in observations
                                  if not o.rendered}, (model_axes, 0))(m, d)


def _mjx_field(d: Any, name: str) -> Any:
    """MjData field `name` of an mjx.Data: a public field, or one the implementation keeps
    under `d._impl` (cfrc_ext, cacc, subtree_linvel, ... differ per implementation); None if
    MJX has no such field."""
    if name in getattr(type(d), "__dataclass_fields__", {}) and name != "_impl":
        return getattr(d, name)
    impl = getattr(d, "_impl", None)
    if impl is not None and name in getattr(type(impl), "__dataclass_fields__", {}):
        return getattr(impl, name)
    return None


def recordable_fields() -> tuple[str, ...]:
    """The MjData field names `record` accepts (besides "state" and "sensor:NAME")."""
    return tuple(sorted(set(mj_batch.DATA_FIELDS) - set(_NOT_VALUES)))


def valid_names(model: mujoco.MjModel) -> list[str]:
    sensors = [SENSOR_PREFIX + layout.object_name(model, mujoco.mjtObj.mjOBJ_SENSOR, i, "sensor")
               for i in range(model.nsensor)]
    return ["state", *sensors, *recordable_fields()]


def parse(model: mujoco.MjModel, record: Any) -> tuple[Observation, ...]:
    """The observations `record` names, validated against the model.

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
        out.append(_observation(model, data, name))
    _check_computed(model, data, [o for o in out if isinstance(o, Field)])
    return tuple(out)


def _observation(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> Observation:
    f64 = np.dtype(np.float64)
    if name == "state":
        nstate = (mujoco.mj_stateSize(model, layout.FULLPHYSICS),)
        return State(name, nstate, f64, layout.FULLPHYSICS, nstate)
    if name.startswith(SENSOR_PREFIX):
        sensor = name[len(SENSOR_PREFIX):]
        i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SENSOR, sensor)
        if i < 0:
            names = [n for n in valid_names(model) if n.startswith(SENSOR_PREFIX)]
            hint = layout.did_you_mean(name, names)
            raise ValueError(f"record: the model has no sensor {sensor!r}{hint}; its sensors: "
                             f"{names or '(none)'}")
        adr, dim = int(model.sensor_adr[i]), int(model.sensor_dim[i])
        return Sensor(name, (dim,), f64, "sensordata", (model.nsensordata,), (adr, adr + dim))
    if name in _NOT_VALUES:
        raise ValueError(f"record: {name} holds {_NOT_VALUES[name]}, not values of the "
                         f"simulation")
    if name == "time":  # a float in MjData, which mujoco.batch records as a state spec
        return Field(name, (), f64, int(mujoco.mjtState.mjSTATE_TIME), (1,))
    if name not in mj_batch.DATA_FIELDS:
        raise ValueError(f"record: {_unknown(model, data, name)}")
    value = getattr(data, name)
    if not isinstance(value, np.ndarray):  # counts (ncon, nefc, ...): int32 per step
        return Field(name, (), np.dtype(np.int32), name, ())
    return Field(name, value.shape, value.dtype, name, value.shape)


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
    return (f"unknown name {name!r}{hint}; valid names: 'state', 'sensordata', 'sensor:NAME' "
            f"for a sensor of the model, and the MjData fields "
            f"{', '.join(recordable_fields())}")


def _check_computed(model: mujoco.MjModel, data: mujoco.MjData, fields: Sequence[Field]) -> None:
    """Refuses floating fields `mj_step` leaves unset for this model: a step from the model's
    defaults must overwrite every value (probed with NaN)."""
    # state components hold the state; sensordata is the sensors' (user sensors without a
    # callback included: the contract's default record)
    unprobed = {*layout.STATE_FIELDS, "sensordata"}
    probed = [f for f in fields if f.floating and f.key not in unprobed and math.prod(f.shape)]
    if not probed:
        return
    mujoco.mj_resetData(model, data)
    for f in probed:
        getattr(data, f.key)[...] = np.nan
    mujoco.mj_step(model, data)
    for f in probed:
        if np.isnan(getattr(data, f.key)).any():
            why = _LAZY.get(f.key, "for this model: its computation is off or absent here")
            raise ValueError(f"record: mj_step leaves {f.key} unset, so it would hold no values "
                             f"of the simulation: MuJoCo computes it {why}")


def check_mjx(observations: Sequence[Observation], data: Any) -> None:
    """Refuses, by name and with the reason, what MJX cannot record.

    Field names are checked against `data`, one trajectory's `mjx.Data` (public fields, and
    those MJX's XLA implementation keeps under `_impl`, `DataJAX`), their shapes and dtype
    kinds against MuJoCo's. Run on the host at construction.

    Raises:
      ValueError: naming every refused observation and why.
    """
    refused = [f"{o.key}: {why}" for o in observations
               if (why := o.mjx_refusal(data)) is not None]
    if refused:
        raise ValueError("record: backend='mjx' cannot record " + "; ".join(refused)
                         + "; use backend='cpu' for these")


def batch_nbytes(observations: Sequence[Observation], nbatch: int, nframes: int, nstep: int,
                 ncontrol: int, nstate: int, itemsize: Optional[int] = None) -> int:
    """Bytes of one batch: the recorded buffers (shared sources counted once), `control`,
    `initial_state` and `diverged`.

    Args:
      itemsize: bytes per floating value where the target stores floats in another precision
        (4 for MJX's float32); None: MuJoCo's (8).
    """
    def nbytes(dtype: np.dtype, count: int) -> int:
        size = itemsize if itemsize is not None and dtype.kind == "f" else dtype.itemsize
        return size * count

    total, sources = 0, set()
    for o in observations:
        if o.source in sources:
            continue
        sources.add(o.source)
        total += nbytes(o.dtype, nbatch * nframes * math.prod(o.source_shape))
    f64 = np.dtype(np.float64)
    return (total + nbytes(f64, nbatch * nstep * ncontrol) + nbytes(f64, nbatch * nstate)
            + nbatch)


def check_batch_fits(config: Any, available: int, where: str, *, count: int,
                     itemsize: Optional[int] = None) -> None:
    """Refuses a batch of `config` (a `SimConfig`) whose `count` copies in flight need more than
    `available` bytes of `where` ("host memory", "GPU memory"); `itemsize` as `batch_nbytes`.

    Raises:
      ValueError: naming `nbatch` and `record`, with the size, what is available and what to
        reduce.
    """
    c = config
    nbytes = batch_nbytes(c.observations, c.nbatch, c.nframes, c.nstep, c.ncontrol, c.nstate,
                          itemsize)
    check_fits(nbytes, available, where, nbatch=c.nbatch, nstep=c.nstep,
               record_every=c.record_every, count=count)


def check_fits(nbytes: int, available: int, where: str, *, nbatch: int, nstep: int,
               record_every: int, count: int = 1) -> None:
    """Refuses a batch of `nbytes` whose `count` copies in flight need more than `available`
    bytes.

    Raises:
      ValueError: with the size, what is available and what to reduce: `nbatch`, or `nstep`
        where not even one trajectory fits.
    """
    if nbytes * count <= available:
        return
    needed = f"{_gib(nbytes)}" + (f" each, {count} in flight ({_gib(nbytes * count)})"
                                  if count > 1 else "")
    fits = nbatch * available // (nbytes * count)
    if fits < 1:  # one trajectory is too long: fewer trajectories would not help
        steps = nstep * available // (-(-nbytes // nbatch) * count)
        raise ValueError(
            f"nstep: a batch of {nbatch} trajectories of {nstep} steps needs {needed}, more "
            f"than the {_gib(available)} of {where} available, and one trajectory alone does "
            f"not fit; use a smaller nstep (about {steps} steps fit with nbatch=1), a larger "
            f"record_every (now {record_every}) or fewer record fields, and continue_episodes="
            f"True for longer episodes")
    raise ValueError(
        f"nbatch, record: a batch needs {needed}, more than the {_gib(available)} of {where} "
        f"available; use a smaller nbatch (at most {fits} fits), a larger record_every (now "
        f"{record_every}), fewer or smaller record fields, or fewer batches in flight "
        f"(prefetch)")


def _gib(n: int) -> str:
    return f"{n / 2**30:.2f} GiB" if n >= 2**27 else f"{n / 2**20:.1f} MiB"


def host_available() -> int:
    """Bytes of host memory available now (Linux MemAvailable; else the physical pages
    free)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import os
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
