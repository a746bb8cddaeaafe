"""Loading models: MJCF/MJB paths, XML strings, MjModel, MjSpec, and the built-in models."""

from __future__ import annotations

import os
import pathlib
from typing import Union

import mujoco

ModelLike = Union[str, os.PathLike, mujoco.MjModel, mujoco.MjSpec]

_ASSETS = pathlib.Path(__file__).parent / "assets"


def builtin_models() -> list[str]:
    """Names of the models shipped with simloader (usable wherever a model is)."""
    return sorted(p.stem for p in _ASSETS.glob("*.xml"))


def builtin_path(name: str) -> pathlib.Path:
    """Path of the built-in model `name` (see `builtin_models()`)."""
    path = _ASSETS / f"{name}.xml"
    if not path.is_file():
        raise ValueError(f"model: no built-in model {name!r}; built-in models are {builtin_models()}")
    return path


def load_model(model: ModelLike) -> mujoco.MjModel:
    """Returns an MjModel for any of the forms `SimDataset(model=...)` accepts.

    Args:
      model: an `MjModel` (used as is), an `MjSpec` (compiled), an XML string (starts with
        `<`), a path to an `.xml` or `.mjb` file, or the name of a built-in model.

    Raises:
      TypeError: `model` is of another type.
      ValueError: the file does not exist or MuJoCo cannot compile it.
    """
    if isinstance(model, mujoco.MjModel):
        return model
    if isinstance(model, mujoco.MjSpec):
        try:
            return model.compile()
        except Exception as e:  # MuJoCo raises its own error types
            raise ValueError(f"model: MjSpec failed to compile: {e}") from e
    if isinstance(model, (str, os.PathLike)):
        text = os.fspath(model)
        if text.lstrip().startswith("<"):
            try:
                return mujoco.MjModel.from_xml_string(text)
            except Exception as e:
                raise ValueError(f"model: XML string failed to compile: {e}") from e
        path = pathlib.Path(text)
        if not path.exists() and path.suffix == "" and (_ASSETS / f"{text}.xml").is_file():
            path = _ASSETS / f"{text}.xml"
        if not path.is_file():
            raise ValueError(
                f"model: expected an MJCF/MJB path, an XML string, an MjModel, an MjSpec or a "
                f"built-in model name {builtin_models()}, got {text!r} (no such file)")
        try:
            if path.suffix.lower() == ".mjb":
                return mujoco.MjModel.from_binary_path(str(path))
            return mujoco.MjModel.from_xml_path(str(path))
        except Exception as e:
            raise ValueError(f"model: {path} failed to load: {e}") from e
    raise TypeError(
        "model: expected an MJCF/MJB path, an XML string, an MjModel or an MjSpec, "
        f"got {type(model).__name__}")


def load_spec(model: ModelLike) -> mujoco.MjSpec:
    """An MjSpec for the forms that have one (MjSpec, XML string, MJCF path, built-in name).

    Raises:
      TypeError: an MjModel or MJB file, which carry no spec (structural variants need one).
    """
    if isinstance(model, mujoco.MjSpec):
        return model
    if isinstance(model, mujoco.MjModel):
        raise TypeError("model: structural variants need an MjSpec, an MJCF path or an XML "
                        "string, got an MjModel (which has no spec)")
    text = os.fspath(model)
    if text.lstrip().startswith("<"):
        return mujoco.MjSpec.from_string(text)
    path = pathlib.Path(text)
    if not path.exists() and (_ASSETS / f"{text}.xml").is_file():
        path = _ASSETS / f"{text}.xml"
    if path.suffix.lower() == ".mjb":
        raise TypeError("model: structural variants need an MJCF model, got an MJB file")
    return mujoco.MjSpec.from_file(str(path))
