"""The suite's streams (`workloads.Stream`) as the `SimDataset`s they name: what the suite's
sides (`suite.py`) and the ranks of a torchrun job (`ranks.py`) build alike."""

from __future__ import annotations

from typing import Any

import mujoco

from simloader.bench import raw as R
from simloader.bench import timing
from simloader.bench.workloads import Stream


def camera_of(s: Stream) -> Any:
    import simloader
    return simloader.Camera(0, height=s.camera[0], width=s.camera[1],
                            shadows=s.camera_quality, multisample=s.camera_quality)


def options(s: Stream, model: mujoco.MjModel) -> dict[str, Any]:
    """`SimDataset` keyword arguments of the stream (besides model, backend and sizes)."""
    import simloader
    from simloader import cli_specs
    out: dict[str, Any] = {"control": simloader.controls.Uniform()}
    record = s.record
    if s.camera is not None:
        record = (*(record or ("state",)), camera_of(s))
    if record:
        out["record"] = record
    if s.terminate:
        out["terminate"] = [cli_specs.parse_terminate(t) for t in s.terminate]
    if s.continue_episodes:
        out["continue_episodes"] = True
    if s.randomize:
        out["randomize"] = [cli_specs.parse_randomize(r) for r in s.randomize]
    if s.policy:  # it picks every step's controls
        device = "cuda" if s.engine in ("mjx", "warp") else "cpu"
        out["policy"] = R.StatePolicy(R.mlp(model.nq + model.nv, model.nu).to(device), model)
        out["control"] = None  # (not the measure's default Uniform)
    if s.engine == "cpu" and s.all_cores:
        out["nthread"] = timing.cpu_count()  # all the cores, as the raw rollout
    return out


def dataset(s: Stream, model: mujoco.MjModel, seed: int, **changes: Any) -> Any:
    """The stream's `SimDataset` (`changes` replace its options)."""
    import simloader
    return simloader.SimDataset(model, backend=s.engine, nbatch=s.nbatch, nstep=s.nstep,
                                seed=seed, **{**options(s, model), **changes})
