"""Loading models: MJCF/MJB paths, XML strings, MjModel, MjSpec, and models by name (the
built-in ones, and Gymnasium's MuJoCo models where `gymnasium` is installed)."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import pathlib
import warnings
from typing import Any, Optional, Union

import mujoco

from simloader import layout

ModelLike = Union[str, os.PathLike, mujoco.MjModel, mujoco.MjSpec]

_ASSETS = pathlib.Path(__file__).parent / "assets"
GYMNASIUM = "gymnasium/"  # prefix of the names of Gymnasium's MuJoCo models


def builtin_models() -> list[str]:
    """Names of the models shipped with simloader (usable wherever a model is)."""
    return sorted(p.stem for p in _ASSETS.glob("*.xml"))


def builtin_path(name: str) -> pathlib.Path:
    """Path of the built-in model `name` (see `builtin_models()`)."""
    path = _ASSETS / f"{name}.xml"
    if not path.is_file():
        raise ValueError(f"model: no built-in model {name!r}; built-in models are "
                         f"{builtin_models()}")
    return path


def _gymnasium_assets() -> Optional[pathlib.Path]:
    """Gymnasium's folder of MuJoCo MJCF files, found without importing Gymnasium."""
    try:
        spec = importlib.util.find_spec("gymnasium")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    path = pathlib.Path(list(spec.submodule_search_locations)[0]) / "envs" / "mujoco" / "assets"
    return path if path.is_dir() else None


def named_models() -> dict[str, tuple[pathlib.Path, str]]:
    """Every model usable by name: {name: (MJCF path, where it comes from)}.

    The built-in models (`cartpole`, `humanoid`), and with `gymnasium` installed (the `gym`
    extra) Gymnasium's MuJoCo models as `gymnasium/NAME` (`gymnasium/hopper`, ...); a
    Gymnasium name without its prefix works too where no built-in model has it.
    """
    out = {name: (builtin_path(name), "built-in") for name in builtin_models()}
    assets = _gymnasium_assets()
    if assets is not None:
        version = importlib.metadata.version("gymnasium")
        for path in sorted(assets.glob("*.xml")):
            out[GYMNASIUM + path.stem] = (path, f"gymnasium {version}")
    return out


def resolve_name(name: str) -> Optional[tuple[pathlib.Path, str]]:
    """(MJCF path, where it comes from) of a model name, or None if no model has it."""
    named = named_models()
    return named.get(name) or named.get(GYMNASIUM + name)


def _names_hint() -> str:
    names = list(named_models())
    if _gymnasium_assets() is None:
        return (f"model names are {names} (Gymnasium's MuJoCo models too, as 'gymnasium/hopper' "
                f"and so on, once gymnasium is installed: python3 -m pip install gymnasium)")
    return f"model names are {names}"


def source(model: Any) -> str:
    """Where a model argument comes from, in words (for `describe()`)."""
    if isinstance(model, mujoco.MjModel):
        return "an MjModel"
    if isinstance(model, mujoco.MjSpec):
        return "an MjSpec"
    text = os.fspath(model)
    if text.lstrip().startswith("<"):
        return "an XML string"
    resolved = _named(text)
    if resolved is not None:
        return f"{text!r}, {resolved[1]}: {resolved[0]}"
    return str(pathlib.Path(text).resolve())


def _named(text: str) -> Optional[tuple[pathlib.Path, str]]:
    """The model a name stands for: one of `named_models()` ("cartpole", "gymnasium/hopper").
    A name is the built-in model even where a file of that name is in the working directory
    (a warning says so); a file is loaded by a path ("./cartpole", "/abs/cartpole") or a
    suffix ("cartpole.xml"). One rule, so that a stray file never replaces a model silently."""
    if pathlib.Path(text).suffix or text.startswith((".", "/", "~")):
        return None  # a path
    return resolve_name(text)


def _path(text: str) -> pathlib.Path:
    """The file a path or model name stands for (ValueError naming the models otherwise)."""
    resolved = _named(text)
    if resolved is not None:
        if pathlib.Path(text).exists():
            warnings.warn(f"model: {text!r} is a built-in model name, and loads the built-in "
                          f"model ({resolved[0]}), not the file {text!r} in the working "
                          f"directory; pass './{text}' to load the file", UserWarning,
                          stacklevel=4)
        return resolved[0]
    path = pathlib.Path(text)
    if path.is_file():
        return path
    raise ValueError(f"model: expected an MJCF/MJB path, an XML string, an MjModel, an MjSpec "
                     f"or a model name, got {text!r} (no such file or model); "
                     + _names_hint())


def describe(model: Any, control_spec: int = int(mujoco.mjtState.mjSTATE_CTRL)) -> str:
    """Where a model comes from and which columns of state, control and sensors mean what.

    Args:
      model: anything `SimDataset` takes as a model (a name, a path, an MjModel, ...).
      control_spec: the mjtState bits of the control vector.
    """
    return layout.describe(load_model(model), control_spec, source=source(model))


def load_model(model: ModelLike) -> mujoco.MjModel:
    """Returns an MjModel for any of the forms `SimDataset(model=...)` accepts.

    Args:
      model: an `MjModel` (used as is), an `MjSpec` (compiled), an XML string (starts with
        `<`), a path to an `.xml` or `.mjb` file, or a model name (`named_models()`).

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
        path = _path(text)
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
    path = _path(text)
    if path.suffix.lower() == ".mjb":
        raise TypeError("model: structural variants need an MJCF model, got an MJB file")
    return mujoco.MjSpec.from_file(str(path))
