"""Whether MJX (its XLA implementation) can simulate a model, said by feature and by object:
asked by `backend="auto"` of MJX when it is about to choose it (`MjxEngine.refuses_model`), by
an explicit `backend="mjx"` before anything is compiled, and by `simloader info`.

MJX's own `put_model` refuses what it cannot simulate by geom *types* ("(mjGEOM_CYLINDER,
mjGEOM_BOX) collisions not implemented"), and its `make_data` raised a bare
`NotImplementedError` for a condim-1 contact under the elliptic cone (MuJoCo Menagerie's Go1).
The checks here walk the same collision pairs as MJX (`collision_driver.geom_pairs`: the
contype/conaffinity filter, explicit pairs, exclusions) with MJX's own table of collision
functions, so that a refusal names the geoms a user would change. What only `put_model` knows
(contact sensors, flex, enum values) is wrapped where it is called (`pool.put_models`).
"""

from __future__ import annotations

import collections
from typing import Optional

import mujoco

from simloader import layout
from simloader.backends import gpu_state

SHOWN = 4  # geom pairs named per refused kind of pair


def _geom(model: mujoco.MjModel, g: int) -> str:
    """A geom by its name, or an unnamed one (most robots' are) by its body's."""
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(g))
    if name:
        return repr(name)
    body = layout.object_name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g]),
                              "body")
    return f"geom {int(g)} of body {body!r}"


def _kind(t: int) -> str:
    return mujoco.mjtGeom(int(t)).name.removeprefix("mjGEOM_").lower()


def condim(model: mujoco.MjModel, g1: int, g2: int, pair: int) -> int:
    """The condim of the contacts of geoms `g1` and `g2` (of explicit pair `pair`, or -1), as
    MuJoCo sets it: the pair's own, else the geom of higher priority's, else the larger."""
    if pair != -1:
        return int(model.pair_dim[pair])
    p1, p2 = model.geom_priority[g1], model.geom_priority[g2]
    if p1 != p2:
        return int(model.geom_condim[g1 if p1 > p2 else g2])
    return int(max(model.geom_condim[g1], model.geom_condim[g2]))


def _listed(pairs: list[str]) -> str:
    """"n geom pairs: the first SHOWN of them and k more"."""
    more = f" and {len(pairs) - SHOWN} more" if len(pairs) > SHOWN else ""
    return (f"{len(pairs)} geom pair{'s' if len(pairs) > 1 else ''}: "
            f"{', '.join(pairs[:SHOWN])}{more}")


def refusal(model: mujoco.MjModel) -> Optional[str]:
    """Why MJX cannot simulate `model`, naming the feature and the objects that use it, or
    None where these checks find nothing (`put_model` may still refuse a rarer feature)."""
    said = gpu_state.unsimulated(model)
    from simloader.backends.mjx import runtime  # noqa: F401 - MJX imported quietly, once
    from mujoco.mjx._src import collision_driver
    missing: dict[tuple[str, str], list[str]] = collections.defaultdict(list)
    margins: list[str] = []
    no_margin = {int(mujoco.mjtGeom.mjGEOM_MESH), int(mujoco.mjtGeom.mjGEOM_HFIELD)}
    single: list[str] = []  # pairs whose contacts have condim 1
    for g1, g2, ip in collision_driver.geom_pairs(model):
        t1, t2 = (int(t) for t in model.geom_type[[g1, g2]])
        pair = f"{_geom(model, g1)} with {_geom(model, g2)}"
        if condim(model, g1, g2, ip) == 1:
            single.append(pair)
        if not collision_driver.has_collision_fn(t1, t2):
            missing[(_kind(t1), _kind(t2))].append(pair)
        elif no_margin & {t1, t2}:
            margin = (model.pair_margin[ip] if ip != -1
                      else model.geom_margin[g1] + model.geom_margin[g2])
            if margin:
                margins.append(pair)
    for (k1, k2), pairs in missing.items():
        said.append(f"{k1}-{k2} collisions ({_listed(pairs)})")
    if margins:
        said.append(f"a margin on mesh or height-field collisions ({_listed(margins)})")
    if model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and single:
        said.append(f"frictionless contacts (condim=1) under the elliptic friction cone "
                    f"({_listed(single)}; <option cone=\"pyramidal\"/> or condim=3 avoids it)")
    if not said:
        return None
    return "MJX does not simulate " + "; ".join(said)
