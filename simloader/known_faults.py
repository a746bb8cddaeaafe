"""Known faults of the simulators simloader runs, from their release notes: which versions,
models and engines each one touches, what it does, and how to avoid it.

`FAULTS` is the one table; a new fault is one more `Fault` row. A dataset whose model meets a
fault on the engine that simulates it warns once at construction (`KnownFaultWarning`) and says
so in `describe()`; a store records the faults its writer met (`recorded`, in its root
attribute) and is flagged when it is opened (`stored_warning`).
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.metadata
import re
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Optional

import mujoco

from simloader import identity


class KnownFaultWarning(RuntimeWarning):
    """The model meets a known fault of the installed simulator on the engine that simulates
    it (or a store was simulated under one): its trajectories may be wrong."""


@dataclasses.dataclass(frozen=True)
class Fault:
    """One known fault of a simulator.

    Attributes:
      name: the fault's name, its project and issue ("mujoco#3767"), as stores record it.
      summary: what goes wrong, in the release notes' words.
      package: the distribution whose versions have it ("mujoco").
      introduced, fixed_in: it is in versions `introduced <= v < fixed_in`.
      engines: the `backend=` engines that run the faulty code.
      applies: whether a model meets it: None, or what of the model does (its options, its
        sizes), in words.
      avoid: the model setting that avoids it on an affected version.
      issue: the issue's address.
    """

    name: str
    summary: str
    package: str
    introduced: str
    fixed_in: str
    engines: tuple[str, ...]
    applies: Callable[[mujoco.MjModel], Optional[str]]
    avoid: str
    issue: str

    def affects(self, version: Optional[str]) -> bool:
        """Whether `version` of `package` has it (None: not installed)."""
        if version is None:
            return False
        return _release(self.introduced) <= _release(version) < _release(self.fixed_in)

    def said(self, version: Optional[str], model: Optional[mujoco.MjModel] = None) -> str:
        """The fault in one sentence: what, where (in `version`, and what of `model` meets it),
        the version that fixes it, how to avoid it."""
        engines = " or ".join(f"backend={engine!r}" for engine in self.engines)
        meets = f" (this model: {self.applies(model)})" if model is not None else ""
        return (f"{self.name} ({self.issue}): {self.package} {version or '?'} on {engines}: "
                f"{self.summary}{meets}; fixed in {self.package} "
                f"{self.fixed_in} (upgrade: python3 -m pip install "
                f"'{self.package}>={self.fixed_in}'), or avoid it with {self.avoid}")


def _newton_sparse(model: mujoco.MjModel) -> Optional[str]:
    # MuJoCo's own rule for the Jacobian's type (jacobian="auto": sparse from nv >= 60)
    if not mujoco.mj_isSparse(model) or model.opt.solver != mujoco.mjtSolver.mjSOL_NEWTON:
        return None
    jacobian = mujoco.mjtJacobian(model.opt.jacobian).name[len("mjJAC_"):].lower()
    return f'solver="Newton", jacobian="{jacobian}" with nv={model.nv}: sparse'


FAULTS: tuple[Fault, ...] = (
    # MuJoCo C's Newton solver, so the CPU engine (mujoco.batch); MJX and MuJoCo Warp have
    # solvers of their own. Renderers draw positions, which the solver does not change.
    Fault(name="mujoco#3767",
          summary="the sparse Cholesky factorization gives the Newton solver a wrong Hessian "
                  "factor when the constraint Jacobian is sparse (jacobian=\"sparse\", or "
                  "\"auto\" with nv >= 60), causing slow convergence, wrong accelerations and "
                  "divergence",
          package="mujoco", introduced="4.0.0", fixed_in="4.0.1", engines=("cpu",),
          applies=_newton_sparse, avoid='<option jacobian="dense"/>',
          issue="https://github.com/google-deepmind/mujoco/issues/3767"),
)
_BY_NAME = {fault.name: fault for fault in FAULTS}
_WARNED: set[tuple[str, str]] = set()  # (fault, model digest) warned of in this process


def _release(version: str) -> tuple[int, ...]:
    """The release numbers of a version ("4.0.1.dev3" -> (4, 0, 1))."""
    found = re.match(r"\d+(\.\d+)*", version)
    if found is None:
        raise ValueError(f"version: expected one starting with release numbers such as "
                         f"'4.0.1', got {version!r}")
    return tuple(int(part) for part in found.group().split("."))


def installed() -> dict[str, Optional[str]]:
    """The installed versions of the packages of `FAULTS` (None: not installed)."""
    return dict(_installed())


@functools.cache  # a process's packages do not change; each look-up is a scan of site-packages
def _installed() -> dict[str, Optional[str]]:
    out: dict[str, Optional[str]] = {}
    for package in {fault.package for fault in FAULTS}:
        try:
            out[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            out[package] = None
    return out


def applying(model: mujoco.MjModel, engine: Optional[str],
             versions: Optional[Mapping[str, Optional[str]]] = None) -> list[Fault]:
    """The known faults `model` meets on `engine`.

    Args:
      model: the model.
      engine: the engine that simulates it (a `backend=` word, "auto" resolved); None: any.
      versions: {package: version} (the shape of a store's recorded versions); None: the
        installed ones.
    """
    versions = installed() if versions is None else versions
    return [fault for fault in FAULTS
            if (engine is None or engine in fault.engines)
            and fault.affects(versions.get(fault.package)) and fault.applies(model) is not None]


def _of_pool(pool: Iterable[mujoco.MjModel], engine: Optional[str],
             versions: Optional[Mapping[str, Optional[str]]] = None
             ) -> dict[str, list[mujoco.MjModel]]:
    """{fault name: the models of `pool` that meet it}, in the order of `FAULTS`."""
    versions = installed() if versions is None else versions
    out: dict[str, list[mujoco.MjModel]] = {}
    for model in pool:
        for fault in applying(model, engine, versions):
            out.setdefault(fault.name, []).append(model)
    return {name: out[name] for name in _BY_NAME if name in out}


def described(pool: Iterable[mujoco.MjModel], engine: Optional[str]) -> list[str]:
    """The lines `describe()` adds: the known faults the models of `pool` meet on `engine`
    (None: on any) with the installed versions."""
    versions = installed()
    return [f"known fault: {_BY_NAME[name].said(versions[_BY_NAME[name].package], models[0])}"
            for name, models in _of_pool(pool, engine, versions).items()]


def warn_once(pool: Iterable[mujoco.MjModel], engine: str, stacklevel: int = 3) -> None:
    """A `KnownFaultWarning` for each known fault the models of `pool` (a dataset's
    `config.pool`) meet on `engine`, once per fault and model (by digest: a model compiled
    again is the same model) per process. `stacklevel`: the user's line, seen from here."""
    versions = installed()
    for name, models in _of_pool(pool, engine, versions).items():
        keys = {(name, identity.model_digest(model)) for model in models}
        if keys <= _WARNED:
            continue
        _WARNED.update(keys)
        fault = _BY_NAME[name]
        said = fault.said(versions[fault.package], models[0])
        warnings.warn(f"simloader: a known fault of the simulator applies to this model, so "
                      f"its trajectories may be wrong: {said}", KnownFaultWarning,
                      stacklevel=stacklevel)


def recorded(dataset: Any) -> list[str]:
    """The names of the known faults a dataset's stream meets (its models on its engine,
    with the installed versions): what a store written from it records (root attribute
    "known_faults")."""
    return list(_of_pool(dataset.config.pool, dataset.config.backend))


def stored_warning(root: Mapping[str, Any],
                   models: Optional[Callable[[], Optional[Sequence[mujoco.MjModel]]]] = None
                   ) -> Optional[str]:
    """What to tell the reader of a store simulated under a known fault, or None.

    Args:
      root: the store's root attribute: its "known_faults" (`recorded` at write time) and
        "versions"; for a store written before simloader recorded them, also its
        "fingerprint" (the engine).
      models: for such a store only, and only where its versions have a fault: returns the
        store's pool of models (`provenance/models/`), or None where the store kept none.
    """
    versions = root.get("versions") or {}
    if "known_faults" in root:
        names = list(root["known_faults"])
    else:
        engine = identity.upgraded(root.get("fingerprint") or {}).get("backend")
        suspects = [f for f in FAULTS
                    if engine in f.engines and f.affects(versions.get(f.package))]
        if not suspects:
            return None
        pool = models() if models is not None else None
        if pool is None:
            # no model to tell by: the faults of its versions on its engine, as conditions
            return ("the store was simulated before simloader recorded the known faults its "
                    "model met, with versions and an engine that have some; its trajectories "
                    "are wrong if the model meets one of: "
                    + "; ".join(f.said(versions[f.package]) for f in suspects))
        names = list(_of_pool(pool, engine, versions))
    if not names:
        return None
    said = [_BY_NAME[n].said(versions.get(_BY_NAME[n].package)) if n in _BY_NAME
            else f"{n} (unknown to this simloader: a newer one recorded it)" for n in names]
    return ("the store was simulated under known fault(s) of the simulator, so its "
            "trajectories may be wrong (write it again with the version that fixes it, or with "
            "the model setting that avoids it): " + "; ".join(said))
