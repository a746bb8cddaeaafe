"""Fuzzing: arbitrary inputs give valid output or a documented exception, never a crash or hang."""

import mujoco
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import simloader

S = mujoco.mjtState
USER_BITS = [int(b) for b in (S.mjSTATE_CTRL, S.mjSTATE_QFRC_APPLIED, S.mjSTATE_XFRC_APPLIED,
                              S.mjSTATE_EQ_ACTIVE, S.mjSTATE_MOCAP_POS, S.mjSTATE_MOCAP_QUAT,
                              S.mjSTATE_USERDATA)]

ODD_MODELS = {
    "empty": "<mujoco/>",
    "no actuators, no sensors": "<mujoco><worldbody><body><freejoint/><geom size='.1'/></body>"
                                "</worldbody></mujoco>",
    "mocap only": "<mujoco><worldbody><body mocap='true'><geom size='.1' contype='0'/></body>"
                  "</worldbody></mujoco>",
    "equality": "<mujoco><worldbody><body name='a'><joint name='j1'/><geom size='.1'/></body>"
                "<body name='b' pos='1 0 0'><joint name='j2'/><geom size='.1'/></body></worldbody>"
                "<equality><joint joint1='j1' joint2='j2'/></equality>"
                "<actuator><motor joint='j1'/></actuator></mujoco>",
    "userdata": "<mujoco><size nuserdata='3'/><worldbody><body><joint/><geom size='.1'/></body>"
                "</worldbody><sensor><clock/></sensor></mujoco>",
}
MODELS = {k: mujoco.MjModel.from_xml_string(v) for k, v in ODD_MODELS.items()}

special = st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, -np.inf, 1e300, -1e300, 1e-300])
values = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64), special)


@st.composite
def cases(draw):
    name = draw(st.sampled_from(sorted(MODELS)))
    model = MODELS[name]
    bits = draw(st.lists(st.sampled_from(USER_BITS), unique=True, max_size=3))
    spec = sum(bits) if draw(st.booleans()) else draw(st.integers(-2, 2 ** 16))
    nbatch = draw(st.integers(1, 4))
    nstep = draw(st.sampled_from([0, 1, 2, 37]))
    kind = draw(st.sampled_from(["none", "array", "generator"]))
    if kind == "array":
        ncontrol = mujoco.mj_stateSize(model, spec) if 0 <= spec and not spec & ~int(
            S.mjSTATE_USER) else 1
        shape = (draw(st.sampled_from([1, nbatch, nbatch + 1])),
                 draw(st.sampled_from([1, max(nstep, 1)])),
                 draw(st.sampled_from([ncontrol, ncontrol + 1])))
        dtype = draw(st.sampled_from([np.float64, np.float32, np.int64, np.bool_]))
        control = np.asarray(draw(st.lists(values, min_size=int(np.prod(shape)),
                                           max_size=int(np.prod(shape))))).reshape(shape)
        with np.errstate(invalid="ignore", over="ignore"):
            control = control.astype(dtype)
    elif kind == "generator":
        control = draw(st.sampled_from([simloader.controls.Uniform(), simloader.controls.Normal(),
                                        simloader.controls.OrnsteinUhlenbeck()]))
    else:
        control = None
    return model, spec, nbatch, nstep, control


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cases())
def test_any_input_gives_output_or_a_documented_error(case):
    model, spec, nbatch, nstep, control = case
    try:
        ds = simloader.SimDataset(model, backend="cpu", nbatch=nbatch, nstep=nstep,
                                  control=control, control_spec=spec, nthread=1)
    except (TypeError, ValueError) as e:
        assert str(e).split(":")[0] in {"nstep", "control", "control_spec", "on"}, str(e)
        return
    batch = next(iter(ds))
    nstate = mujoco.mj_stateSize(model, S.mjSTATE_FULLPHYSICS)
    assert batch["state"].shape == (nbatch, nstep, nstate)
    # nothing non-finite reaches the consumer unflagged
    finite = torch.isfinite(batch["state"]).flatten(1).all(1) & torch.isfinite(
        batch["sensordata"]).flatten(1).all(1)
    assert torch.all(finite | batch["diverged"])


@pytest.mark.parametrize("name", sorted(MODELS))
def test_odd_models_run_with_every_component(name):
    model = MODELS[name]
    spec = int(S.mjSTATE_USER)
    ds = simloader.SimDataset(model, backend="cpu", nbatch=2, nstep=3, nthread=1,
                              control_spec=spec,
                              control=np.zeros((1, 1, mujoco.mj_stateSize(model, spec))))
    batch = next(iter(ds))
    assert batch["control"].shape == (2, 3, mujoco.mj_stateSize(model, spec))
    assert not batch["diverged"].any()
