"""The small specs of `simloader write`'s `--control`, `--randomize` and `--terminate`, read
without `eval`. `--terminate "below(torso, 0.8)"`: a rule of `simloader.terminate` by name.

`--control "ou(std=0.3, tau=0.05)"`: a generator of `simloader.controls` by name (any case,
`ou` for `OrnsteinUhlenbeck`), keyword arguments only. `--randomize
"body_mass:pole=scale:uniform(0.8, 1.2)"`: `FIELD[:OBJ,...]=OP:DIST(ARGS)`, one
`simloader.randomize` parameter (`dr.scale("body_mass", dr.Uniform(0.8, 1.2), on="pole")`).
A spec is parsed as a Python expression (`ast`) and only names, calls of the listed names and
literals (numbers, strings, tuples, True/False/None) are accepted; a bare word is a string.
"""

from __future__ import annotations

import ast
import dataclasses
from typing import Any

from simloader import controls
from simloader import randomize as dr
from simloader import terminate

# lower-case name -> generator (FromArray needs an array: not from the command line)
CONTROLS: dict[str, type] = {
    **{cls.__name__.lower(): cls for cls in (controls.Uniform, controls.Normal,
                                             controls.OrnsteinUhlenbeck,
                                             controls.PiecewiseConstant, controls.Sinusoid,
                                             controls.Constant)},
    "ou": controls.OrnsteinUhlenbeck,
}
DISTRIBUTIONS: dict[str, type] = {cls.__name__.lower(): cls
                                  for cls in (dr.Uniform, dr.LogUniform, dr.Normal)}
OPERATIONS = {"set": dr.set, "scale": dr.scale, "add": dr.add}
RANDOMIZE_FORM = "FIELD[:OBJ,...]=OP:DIST(ARGS)"
RULES: dict[str, type] = {cls.__name__.lower(): cls for cls in (
    terminate.Below, terminate.Tilted, terminate.Outside, terminate.TimeLimit)}


def _arguments(fields: list[str]) -> str:
    return ", ".join(fields) or "(none)"


def _value(node: ast.AST, what: str) -> Any:
    if isinstance(node, ast.Name):  # a bare word: on=pole
        return node.id
    try:
        return ast.literal_eval(node)
    except ValueError:
        raise ValueError(f"{what}: expected a number, a string or a tuple of them, got "
                         f"{ast.unparse(node)!r}") from None


def _call(text: str, option: str, choices: dict[str, type],
          positional: bool) -> tuple[type, list, dict]:
    """(class, args, kwargs) of `name` or `name(...)` in `text`, the name among `choices`."""
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except SyntaxError:
        raise ValueError(f"{option}: cannot read {text!r}; expected NAME or NAME(KEY=VALUE, "
                         f"...), NAME one of {', '.join(choices)}") from None
    call = node if isinstance(node, ast.Call) else None
    name = call.func if call else node
    if not isinstance(name, ast.Name) or name.id.lower() not in choices:
        got = name.id if isinstance(name, ast.Name) else ast.unparse(name)
        raise ValueError(f"{option}: unknown name {got!r} in {text!r}; choices: "
                         f"{', '.join(choices)}")
    cls = choices[name.id.lower()]
    fields = [f.name for f in dataclasses.fields(cls) if f.init]
    if call and call.args and not positional:
        raise ValueError(f"{option}: {name.id} takes keyword arguments only (KEY=VALUE), got "
                         f"{text!r}; its arguments: {_arguments(fields)}")
    args = [_value(a, f"{option}: {name.id}") for a in (call.args if call else ())]
    kwargs = {}
    for kw in call.keywords if call else ():
        if kw.arg not in fields:
            raise ValueError(f"{option}: {name.id} has no argument {kw.arg!r} (in {text!r}); "
                             f"its arguments: {_arguments(fields)}")
        kwargs[kw.arg] = _value(kw.value, f"{option}: {name.id}.{kw.arg}")
    return cls, args, kwargs


def parse_control(text: str) -> controls.Generator:
    """The generator `--control` names, e.g. `"uniform"` or `"ou(std=0.3, tau=0.05)"`.

    Raises:
      ValueError: naming `--control`, what it got and the choices.
    """
    cls, _, kwargs = _call(text, "--control", CONTROLS, positional=False)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ValueError(f"--control: {text!r}: {e}") from None


def parse_terminate(text: str) -> terminate.Rule:
    """The rule `--terminate` names, e.g. `"below(torso, 0.8)"`, `"timelimit(500)"` or
    `"outside(hinge, -0.2, 0.2)"` (positional or keyword arguments; a bare word is a name).

    Raises:
      ValueError: naming `--terminate`, what it got and the choices.
    """
    cls, args, kwargs = _call(text, "--terminate", RULES, positional=True)
    try:
        return cls(*args, **kwargs)
    except (TypeError, ValueError) as e:
        raise ValueError(f"--terminate: {text!r}: {e}") from None


def parse_randomize(text: str) -> dr.Param:
    """The parameter `--randomize` names, `FIELD[:OBJ,...]=OP:DIST(ARGS)`, e.g.
    `"body_mass:pole=scale:uniform(0.8, 1.2)"` or `"dof_damping=add:normal(0, 0.01, low=0)"`.

    Raises:
      ValueError: naming `--randomize`, what it got and the form or choices.
    """
    target, eq, change = text.partition("=")
    op, colon, dist = change.partition(":")
    field, _, on = target.partition(":")
    if not (eq and colon and field.strip() and dist.strip()):
        raise ValueError(f"--randomize: expected {RANDOMIZE_FORM}, e.g. "
                         f"'body_mass:pole=scale:uniform(0.8,1.2)', got {text!r}")
    if op.strip().lower() not in OPERATIONS:
        raise ValueError(f"--randomize: unknown operation {op.strip()!r} in {text!r}; choices: "
                         f"{', '.join(OPERATIONS)}")
    cls, args, kwargs = _call(dist, "--randomize", DISTRIBUTIONS, positional=True)
    try:
        distribution = cls(*args, **kwargs)
    except TypeError as e:
        raise ValueError(f"--randomize: {text!r}: {e}") from None
    objects = [o.strip() for o in on.split(",") if o.strip()]
    return OPERATIONS[op.strip().lower()](field.strip(), distribution, on=objects or None)
