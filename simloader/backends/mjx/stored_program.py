"""Batch functions kept on disk, so that a fresh process does not trace MJX again.

Once JAX's persistent compilation cache holds a batch function's executable, what is left of a
warm start beyond imports is tracing MJX's step in Python and lowering it (the humanoid: about
7 s of 18.6 s on an H200). The first process that compiles a configuration exports its batch
function (`jax.export`: StableHLO, no Python left in it) to

    <compilation cache>/simloader-programs/<key>.jaxexport

and a later process whose key is the same loads it and compiles it, which JAX's persistent
cache answers, without tracing. `compilation_cache=False` turns this off with JAX's cache.

The key is a SHA-256 of everything the traced program is made from:
- the configuration's fingerprint (`identity.fingerprint`: models by the digest of their saved
  binary, control generators and their parameters, records, initial states, randomization,
  backend options, dtype) without what enters the function as an argument (seed,
  num_batches);
- the shape and dtype of every argument;
- the platform and device kind, and `jax_enable_x64`;
- the versions of jax, jaxlib, mujoco and mujoco-mjx, and a digest of simloader's own source
  files, so that an edited checkout never runs a program traced from other code.
A stale entry is therefore never found: any change gives another key. An entry that cannot be
read is said to be ignored, traced again and replaced. JAX checks the arguments' shapes and
dtypes against the program at every call besides.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import os
import pathlib
import sys
from collections.abc import Sequence
from typing import Any, Optional

import jax

from simloader import identity
from simloader.atomic import atomic_write

FOLDER = "simloader-programs"
SUFFIX = ".jaxexport"
# timings of the last cold compile per model, shown while the next one compiles
TIMINGS = "compile-times.json"
# settings that do not enter the program: they reach it as arguments
_ARGUMENTS = ("seed", "num_batches")


@functools.cache
def source_digest() -> str:
    """A digest of simloader's Python sources (the package this module belongs to)."""
    root = pathlib.Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _version(name: str) -> Optional[str]:
    try:
        return importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
        return None


def key(config: Any, device: jax.Device, leaves: Sequence[Any]) -> str:
    """The key of the program of `config` on `device` called with `leaves` (the flattened
    arguments): equal only if everything the program is traced from is equal."""
    fingerprint = {k: v for k, v in identity.fingerprint(config).items() if k not in _ARGUMENTS}
    traced_from = {
        "fingerprint": fingerprint,
        "arguments": [[list(leaf.shape), str(leaf.dtype)] for leaf in leaves],
        "platform": device.platform, "device_kind": device.device_kind,
        "x64": bool(jax.config.jax_enable_x64),
        "versions": {name: _version(name) for name in ("jax", "jaxlib", "mujoco",
                                                       "mujoco-mjx", "simloader")},
        "source": source_digest(),
    }
    text = json.dumps(traced_from, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def store_for(cache: Any) -> Optional["ProgramStore"]:
    """The program store beside JAX's compilation cache `cache`, or None: `cache` is False, or
    JAX cannot serialize programs here (its `flatbuffers` dependency is missing: said once)."""
    if cache is False:
        return None
    if importlib.util.find_spec("flatbuffers") is None:
        _missing_once()
        return None
    return ProgramStore(cache)


@functools.cache
def _missing_once() -> None:
    _say("batch functions are not kept for later processes, which trace them again: "
         "jax.export needs the flatbuffers package (pip install 'simloader[mjx]')")


class ProgramStore:
    """The folder of exported batch functions beside JAX's compilation cache.

    Args:
      cache: JAX's persistent compilation cache directory (`MjxOptions.compilation_cache`).
    """

    def __init__(self, cache: str):
        self.folder = os.path.join(cache, FOLDER)

    def path(self, key: str) -> str:
        return os.path.join(self.folder, key + SUFFIX)

    def load(self, key: str) -> Optional[jax.export.Exported]:
        """The program stored under `key`, or None: none stored, or one that cannot be read
        (said on stderr; it is traced again and replaced)."""
        path = self.path(key)
        try:
            with open(path, "rb") as f:
                blob = f.read()
        except FileNotFoundError:
            return None
        except OSError as error:
            _say(f"cannot read the stored program {path} ({error}); tracing again")
            return None
        try:
            return jax.export.deserialize(bytearray(blob))
        except Exception as error:  # noqa: BLE001 (a truncated or foreign file: trace again)
            _say(f"ignoring the stored program {path}, which cannot be loaded "
                 f"({type(error).__name__}: {error}); tracing again")
            return None

    def save(self, key: str, exported: jax.export.Exported) -> None:
        """Stores `exported` under `key`, whole or not at all (written aside, then renamed).
        A folder that cannot be written costs the next process a trace, nothing more."""
        try:
            atomic_write(self.path(key), [exported.serialize()])
        except OSError as error:
            _say(f"cannot store the batch function in {self.folder} ({error}); the next "
                 f"process traces it again")

    def last_compile_s(self, model_digest: str) -> Optional[float]:
        """Seconds the last cold compile of a configuration of this model took, if known."""
        seconds = self._timings().get(model_digest)
        return float(seconds) if isinstance(seconds, (int, float)) else None

    def note_compile_s(self, model_digest: str, seconds: float) -> None:
        timings = {**self._timings(), model_digest: round(seconds, 1)}
        try:
            atomic_write(os.path.join(self.folder, TIMINGS), [json.dumps(timings).encode()])
        except OSError:
            pass  # only a hint for the next cold start

    def _timings(self) -> dict:
        """{model digest: seconds of its last cold compile}; {} if unknown or unreadable."""
        try:
            with open(os.path.join(self.folder, TIMINGS)) as f:
                timings = json.load(f)
        except (OSError, ValueError):
            return {}
        return timings if isinstance(timings, dict) else {}


def _say(message: str) -> None:
    print(f"simloader: {message}", file=sys.stderr, flush=True)
