"""Episodes that end where the task ends: termination rules, for `SimDataset(terminate=...)`.

A rule is data: what it looks at (a body's height, its tilt, a joint's position, the episode's
length) and a test written once over the array module (NumPy, torch or jax.numpy), which each
engine evaluates inside its own step loop on the state of every recorded frame. After a
frame whose state meets a rule, the trajectory's next frame is a fresh initial state
(autoreset); the frames are flagged in `batch["terminated"]`, `batch["truncated"]` (a
`TimeLimit`) and `batch["first"]` (the fresh initial states).

    terminate=simloader.terminate.Below("torso", 0.8)            # a fallen walker
    terminate=[Tilted("torso", 1.0), TimeLimit(500)]             # any one ends the episode
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any, Optional

import mujoco
import numpy as np

from simloader import layout

# fresh initial states an initial-state generator draws per trajectory and batch for the
# autoreset: a trajectory's e-th reset within a batch takes draw e mod FRESH_DRAWS (each seeded
# by batch and draw, so streams stay reproducible and resumable, and engines agree)
FRESH_DRAWS = 8

# the rules as rows of a table (`Rule.row`): kind -> code, for an engine that evaluates them in
# a kernel of its own (MuJoCo Warp's): outside: qpos[index] < a or > b; below: xpos[index, 2]
# < a; tilted: xmat[index, 8] (the cosine of the body's tilt) < a
KINDS = {"outside": 0, "below": 1, "tilted": 2}

# what a rule may read of a frame's state, as each engine hands it over: name -> shape after
# (nbatch,). Kinematics (xpos, xmat) are those of the frame's own state (mj_kinematics of it).
FIELDS = ("qpos", "xpos", "xmat")


class Rule:
    """A termination rule (a frozen dataclass): `reads` the fields of a frame's state it looks
    at, `resolve(model)` checks it against the model, and `met(xp, fields)` says, for every
    trajectory, whether the frame's state meets it."""

    reads: tuple[str, ...] = ()
    # how to make one (the refusal of a class given for an instance shows it)
    example = "Below('torso', 0.8)"

    def row(self) -> tuple[int, int, float, float]:
        """The resolved rule as one row of a table an engine's kernel reads: (kind, index,
        a, b), kinds in `KINDS` (what `met` computes, spelled as data)."""
        raise NotImplementedError

    def resolve(self, model: mujoco.MjModel) -> "Rule":
        """The rule with its names resolved against `model` (ids filled in).

        Raises:
          ValueError: an unknown name, naming the rule and the model's choices.
        """
        return self

    def met(self, xp: Any, fields: dict[str, Any]) -> Any:
        """(nbatch,) bool: the frame's state meets the rule; `fields`: {name in `reads`:
        (nbatch, ...) array of module `xp`}."""
        raise NotImplementedError


def _name(rule: str, what: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise TypeError(f"terminate: {rule}'s {what} must be a name (str), got "
                        f"{type(value).__name__} {value!r}")
    return value


def _number(rule: str, what: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value):
        raise ValueError(f"terminate: {rule}'s {what} must be a finite number, got {value!r}")
    return float(value)


def _moving_body(model: mujoco.MjModel, name: str, rule: str, fixed: str) -> int:
    """The id of body `name`, which must not be the world body: it never moves (`fixed`: what
    the rule would read there), so the rule would be met at every frame or never."""
    body = _object_id(model, mujoco.mjtObj.mjOBJ_BODY, "body", name, rule)
    if body == 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i)
                 for i in range(1, model.nbody)]
        raise ValueError(f"terminate: {rule}: body {name!r} is the world body, which never "
                         f"moves ({fixed}): name a body that moves (the model's other "
                         f"bodies: {[n for n in names if n] or '(none)'})")
    return body


def _object_id(model: mujoco.MjModel, kind: mujoco.mjtObj, what: str, name: str,
               rule: str) -> int:
    found = mujoco.mj_name2id(model, kind, name)
    if found < 0:
        count = {mujoco.mjtObj.mjOBJ_BODY: model.nbody, mujoco.mjtObj.mjOBJ_JOINT: model.njnt}[kind]
        names = [mujoco.mj_id2name(model, kind, i) for i in range(count)]
        names = [n for n in names if n]
        raise ValueError(f"terminate: {rule}: the model has no {what} {name!r}"
                         f"{layout.did_you_mean(name, names)}; its {what}s: {names or '(none)'}")
    return found


@dataclasses.dataclass(frozen=True)
class Below(Rule):
    """The body's world height `xpos[body, 2]` is below `height` (metres): a fallen walker.

    Args:
      body: the body's name.
      height: the height limit, in metres (any sign).
    """

    body: str
    height: float
    body_id: int = dataclasses.field(default=-1, compare=False, repr=False)
    # the qpos column of the body's height where a free joint alone moves it (-1: none):
    # mj_kinematics copies a free joint's position into xpos (MuJoCo C, MJX and MuJoCo Warp
    # alike), so the rule reads that column and no engine runs the kinematics for it (4% of a
    # humanoid's Warp step)
    # (derived: from the model, so not part of a stream's fingerprint, `identity`)
    free_z: int = dataclasses.field(default=-1, compare=False, repr=False,
                                    metadata={"derived": True})

    def __post_init__(self):
        _name("Below", "body", self.body)
        object.__setattr__(self, "height", _number("Below", "height", self.height))

    @property
    def reads(self) -> tuple[str, ...]:  # type: ignore[override]
        return ("qpos",) if self.free_z >= 0 else ("xpos",)

    def resolve(self, model):
        body = _moving_body(model, self.body, f"Below({self.body!r}, {self.height})",
                            "its height is always 0")
        joint = model.body_jntadr[body]
        free = (model.body_jntnum[body] == 1
                and model.jnt_type[joint] == mujoco.mjtJoint.mjJNT_FREE)
        return dataclasses.replace(self, body_id=body,
                                   free_z=int(model.jnt_qposadr[joint]) + 2 if free else -1)

    def met(self, xp, fields):
        if self.free_z >= 0:
            return fields["qpos"][:, self.free_z] < self.height
        return fields["xpos"][:, self.body_id, 2] < self.height

    def row(self):
        if self.free_z >= 0:  # outside(free_z, height, +inf): the same test on the column
            return (KINDS["outside"], self.free_z, self.height, math.inf)
        return (KINDS["below"], self.body_id, self.height, 0.0)


@dataclasses.dataclass(frozen=True)
class Tilted(Rule):
    """The body's z axis is more than `max_angle` radians from the world's z axis: a robot on
    its side.

    Args:
      body: the body's name.
      max_angle: the largest tilt allowed, in radians, in (0, pi].
    """

    body: str
    max_angle: float
    body_id: int = dataclasses.field(default=-1, compare=False, repr=False)
    reads = ("xmat",)
    example = "Tilted('torso', 1.0)"

    def __post_init__(self):
        _name("Tilted", "body", self.body)
        angle = _number("Tilted", "max_angle", self.max_angle)
        if not 0 < angle <= math.pi:
            raise ValueError(f"terminate: Tilted({self.body!r}, ...)'s max_angle must be in "
                             f"(0, pi] radians, got {self.max_angle!r}")
        object.__setattr__(self, "max_angle", angle)

    def resolve(self, model):
        body = _moving_body(model, self.body, f"Tilted({self.body!r}, {self.max_angle})",
                            "its tilt is always 0")
        return dataclasses.replace(self, body_id=body)

    def met(self, xp, fields):
        # xmat is row-major: element 8 is the z component of the body's z axis, the cosine of
        # its angle to the world's z axis
        return fields["xmat"][:, self.body_id, 8] < math.cos(self.max_angle)

    def row(self):
        return (KINDS["tilted"], self.body_id, math.cos(self.max_angle), 0.0)


@dataclasses.dataclass(frozen=True)
class Outside(Rule):
    """A 1-dof joint's position (`qpos` of a slide or hinge joint) leaves `[low, high]`: a cart
    past the rail's end, a pole past an angle.

    Args:
      joint: the joint's name (a slide or hinge joint).
      low, high: the interval it must stay in (metres or radians), low < high.
    """

    joint: str
    low: float
    high: float
    qpos_adr: int = dataclasses.field(default=-1, compare=False, repr=False)
    reads = ("qpos",)
    example = "Outside('hinge', -0.2, 0.2)"

    def __post_init__(self):
        _name("Outside", "joint", self.joint)
        low = _number("Outside", "low", self.low)
        high = _number("Outside", "high", self.high)
        if not low < high:
            raise ValueError(f"terminate: Outside({self.joint!r}, {self.low!r}, {self.high!r}): "
                             f"expected low < high")
        object.__setattr__(self, "low", low)
        object.__setattr__(self, "high", high)

    def resolve(self, model):
        what = f"Outside({self.joint!r}, {self.low}, {self.high})"
        joint = _object_id(model, mujoco.mjtObj.mjOBJ_JOINT, "joint", self.joint, what)
        kind = int(model.jnt_type[joint])
        if kind not in (mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE):
            one_dof = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
                       for j in range(model.njnt) if int(model.jnt_type[j]) in
                       (mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE)]
            raise ValueError(f"terminate: {what}: joint {self.joint!r} is a "
                             f"{mujoco.mjtJoint(kind).name[6:].lower()} joint; Outside takes a "
                             f"1-dof joint (slide or hinge): {one_dof or '(none)'}")
        return dataclasses.replace(self, qpos_adr=int(model.jnt_qposadr[joint]))

    def met(self, xp, fields):
        q = fields["qpos"][:, self.qpos_adr]
        return (q < self.low) | (q > self.high)

    def row(self):
        return (KINDS["outside"], self.qpos_adr, self.low, self.high)


@dataclasses.dataclass(frozen=True)
class TimeLimit(Rule):
    """The episode is truncated after `steps` physics steps (a reset frame is step 0; with
    `continue_episodes=True` the count runs across batches). Checked at the recorded frames:
    with `record_every=k`, the first frame at or past `steps`.

    Args:
      steps: the episode's length in steps, >= 1.
    """

    steps: int
    example = "TimeLimit(500)"

    def __post_init__(self):
        if isinstance(self.steps, bool) or not isinstance(self.steps, (int, np.integer)) \
                or self.steps < 1:
            raise ValueError(f"terminate: TimeLimit(steps)'s steps must be an int >= 1, got "
                             f"{self.steps!r}")

    # (no `met`: a time limit reads no state; `Episodes.truncated` counts the steps)


@dataclasses.dataclass(frozen=True)
class Episodes:
    """The resolved `terminate=` of a dataset: its rules (checked against the model), what
    they read, and the time limit if any.

    Attributes:
      rules: the rules that terminate an episode, resolved.
      time_limit: a `TimeLimit`'s steps, or None.
      reads: the fields of a frame's state the rules read (a subset of `FIELDS`).
      check: a callable `obs -> (nbatch,) bool tensor` over the observations a policy would
        get (the records, as torch tensors), called after every recorded frame where the
        engine steps from Python (the CPU and Warp engines), or None.
    """

    rules: tuple[Rule, ...]
    time_limit: Optional[int]
    reads: tuple[str, ...]
    check: Any = dataclasses.field(default=None, compare=False)

    def checked(self, obs: dict[str, Any], frame: int, nbatch: int) -> Any:
        """(nbatch,) bool tensor: `check` on frame `frame`'s observations, its result checked.

        Raises:
          ValueError: not a bool tensor of shape (nbatch,) on the observations' device,
            naming the frame.
        """
        import torch
        out = self.check(obs)
        # the engine combines the verdict with its own flags there (a meta or another
        # device's tensor would fail inside the engine, with torch's words)
        device = next((v.device for v in obs.values() if isinstance(v, torch.Tensor)), None)
        if not (isinstance(out, torch.Tensor) and out.dtype == torch.bool
                and tuple(out.shape) == (nbatch,) and (device is None or out.device == device)):
            got = type(out).__name__
            if isinstance(out, torch.Tensor):
                got = f"{out.dtype} tensor of shape {tuple(out.shape)}" + (
                    f" on {out.device}" if device is not None and out.device != device else "")
            name = getattr(self.check, "__name__", type(self.check).__name__)
            where = "" if device is None else f" on {device} (the observations' device)"
            raise ValueError(f"terminate: the callable {name!r} must return a bool tensor of "
                             f"shape ({nbatch},){where} (nbatch: does each trajectory's "
                             f"episode end?), got {got} at frame {frame}")
        return out

    @property
    def kinematic(self) -> bool:
        """Whether a rule reads what mj_kinematics derives from the state (xpos, xmat)."""
        return any(f != "qpos" for f in self.reads)

    def terminated(self, xp: Any, fields: dict[str, Any], like: Any) -> Any:
        """(nbatch,) bool: a frame's state meets a terminating rule (`like`: an (nbatch,)
        bool array of the module, returned False when there are no such rules)."""
        out = xp.zeros_like(like)
        for rule in self.rules:
            out = out | rule.met(xp, fields)
        return out

    def truncated(self, xp: Any, episode_steps: Any, like: Any) -> Any:
        """(nbatch,) bool: the time limit ends the episode at a frame after `episode_steps`
        steps (`like`: as `terminated`'s)."""
        if self.time_limit is None:
            return xp.zeros_like(like)
        return episode_steps >= self.time_limit


def parse(model: mujoco.MjModel, terminate: Any) -> Optional[Episodes]:
    """The `Episodes` of `terminate=`: None, a rule, or a sequence of rules (any one ends the
    episode; at most one `TimeLimit`).

    Raises:
      ValueError, TypeError: a rule that does not fit the model, or a value that is not one.
    """
    if terminate is None:
        return None
    single = isinstance(terminate, Rule) or (callable(terminate)
                                             and not isinstance(terminate, Sequence))
    rules = [terminate] if single else terminate
    if not isinstance(rules, Sequence) or isinstance(rules, (str, bytes)) or not rules:
        raise TypeError(f"terminate: expected None, a rule of simloader.terminate (Below, "
                        f"Tilted, Outside, TimeLimit), a callable obs -> (nbatch,) bool tensor, "
                        f"or a non-empty sequence of them, got {terminate!r}")
    for r in rules:
        if isinstance(r, type):  # callable, but calling it makes an object, never a verdict
            such = (f"such as {r.example}" if issubclass(r, Rule)
                    else "(a rule of simloader.terminate or a callable obs -> (nbatch,) bool "
                         "tensor), not its class")
            raise TypeError(f"terminate: got the class {r.__name__}, expected an instance "
                            f"{such}")
    checks = [r for r in rules if callable(r) and not isinstance(r, Rule)]
    bad = [r for r in rules if not isinstance(r, Rule) and not callable(r)]
    if bad:
        raise TypeError(f"terminate: expected rules of simloader.terminate (Below, Tilted, "
                        f"Outside, TimeLimit) or a callable, got {bad[0]!r}")
    if len(checks) > 1:
        raise ValueError(f"terminate: at most one callable, got {len(checks)}")
    rules = [r for r in rules if isinstance(r, Rule)]
    limits = [r for r in rules if isinstance(r, TimeLimit)]
    if len(limits) > 1:
        raise ValueError(f"terminate: at most one TimeLimit, got {limits}")
    resolved = tuple(r.resolve(model) for r in rules if not isinstance(r, TimeLimit))
    reads = tuple(f for f in FIELDS if any(f in r.reads for r in resolved))
    return Episodes(resolved, limits[0].steps if limits else None, reads,
                    checks[0] if checks else None)
