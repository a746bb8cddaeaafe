"""A configuration's identity: what must match for a saved stream to resume, a store to be
regenerated, or a traced program to be loaded again (the resume state, the data store and the
program store all use it), and how two identities differ, named field by field.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, Optional

import mujoco
import numpy as np

from simloader.config import SimConfig


# an engine's option field that does not change the stream (where JAX caches, how much memory
# it takes) says so in its metadata: dataclasses.field(metadata={STREAM_UNCHANGED[0]: False})
STREAM_UNCHANGED = ("stream", False)


# (backend, impl) saved before the engines had one vocabulary -> today's word: the registry
# (backends/__init__.py, which holds the older spellings) fills it when it loads
OLD_SPELLINGS: dict[tuple[str, Optional[str]], str] = {}


def upgraded(saved: Any) -> Any:
    """A fingerprint saved before the engines had one vocabulary (a state_dict or a store's
    provenance), in today's words (`OLD_SPELLINGS`: the same stream, so it resumes). Others
    as they are."""
    if not isinstance(saved, dict):
        return saved
    options = saved.get("backend_options")
    impl = options.get("impl") if isinstance(options, dict) else None
    key = (saved.get("backend"), impl)
    new = OLD_SPELLINGS.get(key) if all(isinstance(k, (str, type(None))) for k in key) \
        else None
    if new is None:
        return saved
    out = dict(saved, backend=new)
    if isinstance(options, dict):
        out["backend_options"] = {k: v for k, v in options.items() if k != "impl"}
    return out


def model_digest(model: mujoco.MjModel) -> str:
    """A digest of everything in `model` (its saved binary)."""
    buffer = np.empty(mujoco.mj_sizeModel(model), dtype=np.uint8)
    mujoco.mj_saveModel(model, None, buffer)
    return hashlib.sha256(buffer.tobytes()).hexdigest()[:16]


def fingerprint(config: SimConfig) -> dict[str, Any]:
    """What must match for a saved stream to resume: everything that changes the stream (sizes,
    seed, backend and its resolved options, the models, controls, initial states,
    randomization, dtype), as JSON values that are the same in every process (arrays and
    models by digest)."""
    models = config.models or (config.model,)
    plan = config.control
    control = (None if plan.fixed is None and not plan.drivers else
               _describe(plan.fixed) if plan.fixed is not None else
               [{"generator": _describe(d.generator), "columns": _describe(d.columns)}
                for d in plan.drivers])
    init = config.initial
    randomize = None
    if config.randomization is not None:
        randomize = [_describe(r.param) for r in config.randomization.resolved]
    elif config.variants is not None:
        randomize = {"variants": [model_digest(m) for m in config.variants]}
    # a batch split across simulation devices draws each part from its own stream
    split = {} if config.parts is None or len(config.parts) == 1 else {
        "sim_parts": [p.nbatch for p in config.parts]}
    return {
        **split,
        "backend": config.backend, "nbatch": config.nbatch, "nstep": config.nstep,
        "control_spec": config.control_spec, "seed": config.seed,
        "continue_episodes": config.continue_episodes, "num_batches": config.num_batches,
        "model": hashlib.sha256("".join(model_digest(m) for m in models).encode()
                                ).hexdigest()[:16],
        "control": control,
        "record": [o.key for o in config.observations], "record_every": config.record_every,
        "initial_state": (_describe(init.generator) if init.generator is not None else
                          {"keyframe": init.keyframe} if init.from_model else
                          _describe(init.fixed)),
        "randomize": randomize,
        # a policy changes the stream (its weights are the training's, not the stream's)
        "policy": config.policy is not None,
        "policy_noise": None if config.policy_noise is None else [
            {"generator": _describe(d.generator), "columns": _describe(d.columns)}
            for d in config.policy_noise.drivers],
        "dtype": None if config.dtype is None else str(config.dtype),
        # absent without rules, so that the fingerprints of streams without them stay as saved
        **({} if getattr(config, "terminate", None) is None else {"terminate": {
            "rules": [_describe(r) for r in config.terminate.rules],
            "time_limit": config.terminate.time_limit,
            "check": _describe(config.terminate.check)}}),
        "backend_options": {k: _describe(v) for k, v in sorted(_options(config.options).items())},
        # absent by default, so that the fingerprints of streams saved before it stay
        **({} if getattr(config, "record_kinematics", "before_step") == "before_step" else
           {"record_kinematics": config.record_kinematics}),
    }


def _options(options: Any) -> dict[str, Any]:
    """A backend's resolved options (`SimConfig.options`: a dataclass; None in configurations
    saved before the CPU backend had one) by name."""
    if options is None:
        return {}
    if dataclasses.is_dataclass(options):
        # a field left out of comparisons is not part of what the options are (e.g. models
        # already put on a device, kept for reuse)
        key, unchanged = STREAM_UNCHANGED
        return {f.name: getattr(options, f.name) for f in dataclasses.fields(options)
                if f.compare and f.metadata.get(key, True) is not unchanged}
    return dict(vars(options))


def _describe(value: Any) -> Any:
    """A JSON value that identifies `value` in any process: dataclasses (generators,
    distributions, parameters) by type and fields, small arrays as lists, large ones and
    models by digest, functions by qualified name; never an address."""
    if isinstance(value, float) or isinstance(value, np.floating):
        return float(value) if np.isfinite(value) else str(float(value))
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, mujoco.MjModel):
        return {"model": model_digest(value)}
    if isinstance(value, (np.ndarray, np.generic)) or hasattr(value, "__array__"):
        array = np.asarray(value)
        if array.size <= 16:
            return _describe(array.tolist())
        return {"shape": list(array.shape), "dtype": array.dtype.str,
                "sha256": hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        # a field marked `derived` is computed from the model (digested already): left out,
        # so that fingerprints saved before it existed still match
        return {"type": _qualname(type(value)),
                **{f.name: _describe(getattr(value, f.name)) for f in dataclasses.fields(value)
                   if not f.metadata.get("derived")}}
    if isinstance(value, dict):
        return {str(k): _describe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_describe(v) for v in value]
    if callable(value) and hasattr(value, "__qualname__"):
        return _qualname(value)
    fields = {k: _describe(v) for k, v in sorted(getattr(value, "__dict__", {}).items())}
    return {"type": _qualname(type(value)), **fields}


def _qualname(obj: Any) -> str:
    return f"{getattr(obj, '__module__', '?')}.{getattr(obj, '__qualname__', type(obj).__name__)}"


def _leaves(value: Any, path: str) -> dict[str, Any]:
    """{dotted path: leaf value} of a nested JSON value, so differences can be named."""
    if isinstance(value, dict) and value:
        out = {}
        for k, v in value.items():
            out.update(_leaves(v, f"{path}.{k}"))
        return out
    if isinstance(value, list) and value and any(isinstance(v, dict) for v in value):
        out = {f"{path}.length": len(value)}
        for i, v in enumerate(value):
            out.update(_leaves(v, f"{path}[{i}]"))
        return out
    return {path: value}


def short(value: Any) -> str:
    """A value's repr, cut to 60 characters (for messages naming differences)."""
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def differences(expected: dict, saved: Any) -> list[tuple[str, Any, Any]]:
    """(dotted path, expected value, saved value) of every leaf where two fingerprints
    differ, nested values named down to the field that differs."""
    saved = saved if isinstance(saved, dict) else {}
    out = []
    for key in list(expected) + [k for k in saved if k not in expected]:
        here, there = _leaves(expected.get(key), key), _leaves(saved.get(key), key)
        if (key in here) != (key in there) or type(expected.get(key)) is not type(saved.get(key)):
            here, there = {key: expected.get(key)}, {key: saved.get(key)}  # another kind
        out += [(k, here.get(k), there.get(k))
                for k in list(here) + [k for k in there if k not in here]
                if here.get(k) != there.get(k)]
    return out
