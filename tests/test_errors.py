"""Bad input fails at construction with a message naming the argument, expected and actual."""

import re
import threading

import mujoco
import numpy as np
import pytest

import simloader
from simloader import controls

S = mujoco.mjtState


def make(model="cartpole", **kwargs):
    args = dict(backend="cpu", nbatch=4, nstep=10)
    args.update(kwargs)
    return simloader.SimDataset(model, **args)


CASES = [
    (dict(control=np.zeros((4, 10, 2))), ValueError,
     "control: trailing dimension must be 1 (nu=1), got 2"),
    (dict(control=np.zeros((4, 10, 8)), control_spec=int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED)),
     ValueError, "control: trailing dimension must be 3 (nu=1 + nv=2), got 8"),
    (dict(control=np.zeros((3, 10, 1))), ValueError,
     "control: leading dimension must be nbatch=4 or 1, got 3"),
    (dict(control=np.zeros((4, 7, 1))), ValueError,
     "control: second dimension must be nstep=10 or 1, got 7"),
    (dict(control=np.zeros((10, 1))), ValueError,
     "control: expected 3 dimensions [nbatch or 1] x [nstep or 1] x ncontrol, got shape (10, 1)"),
    (dict(control="uniform"), TypeError, "control: expected None, an array"),
    (dict(control_spec=int(S.mjSTATE_QPOS)), ValueError,
     "control_spec: expected bits within mjSTATE_USER (8128), got 2 (bits 2 are outside)"),
    (dict(control_spec=1.5), TypeError, "control_spec: expected an mjtState bitmask (int) or "
     "component names ('ctrl|xfrc_applied'), got float"),
    (dict(initial_state="nope"), ValueError,
     "initial_state: unknown keyframe 'nope'; the model's keyframes are ['upright', 'hanging']"),
    (dict(initial_state=np.full((1, 5), np.nan)), ValueError,
     "initial_state: expected finite values, got nan at index (0, 0)"),
    (dict(initial_state=np.zeros((4, 6))), ValueError,
     "initial_state: trailing dimension must be nstate=5 (mjSTATE_FULLPHYSICS), got 6"),
    (dict(initial_state=np.zeros((2, 5))), ValueError,
     "initial_state: leading dimension must be nbatch=4 or 1, got 2"),
    (dict(nbatch=0), ValueError, "nbatch: expected an integer >= 1, got 0"),
    (dict(nstep=2.0), TypeError, "nstep: expected an integer, got float 2.0"),
    (dict(num_batches=-1), ValueError, "num_batches: expected None or an integer >= 1, got -1"),
    (dict(seed="x"), TypeError, "seed: expected an integer, got str 'x'"),
    (dict(backend="gpu"), ValueError, "backend: expected one of ('auto', 'cpu', 'mjx', 'warp'), got 'gpu'"),
    (dict(continue_episodes=1), TypeError, "continue_episodes: expected a bool, got int"),
    (dict(dtype="int8"), ValueError, "dtype: expected None, torch.float32 or torch.float64, got 'int8'"),
    (dict(device="tpu"), ValueError, "device: expected None, 'cpu', 'cuda' or 'cuda:N', got 'tpu'"),
    (dict(randomize=[]), ValueError, "randomize: expected nbatch=4 models (one per trajectory), got 0"),
    (dict(randomize="models"), TypeError, "randomize: expected None, a sequence of MjModel (one per trajectory)"),
    (dict(control={"xfrc_applied": controls.Uniform()}), ValueError,
     "control: 'xfrc_applied' is not a component of control_spec; its components are ['ctrl']"),
    (dict(control=controls.Uniform(on="pusher")), ValueError,
     "on: ctrl has no object 'pusher' (did you mean 'push'?); its objects are ['push']"),
    (dict(control=controls.Uniform(low=1.0, high=0.0)), ValueError,
     "Uniform: expected finite low <= high"),
    (dict(control=controls.Normal(std=[1.0, 2.0])), ValueError,
     "Normal.std: expected a scalar, 1 values (one object of ctrl) or 1 values"),
    (dict(control=controls.Uniform(), control_spec=int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED)),
     TypeError, "control: a single generator drives one control_spec component, but control_spec "
                "has 2 (ctrl, qfrc_applied): pass a dict {component: generator}"),
    (dict(control={"ctrl": [controls.Uniform(), controls.Normal()]}), ValueError,
     "control['ctrl']: column 0 of ctrl (push) is driven twice"),
    (dict(initial_state=simloader.initial.Perturbed(qpos_std=-1.0)), ValueError,
     "Perturbed.qpos_std: expected a finite number >= 0, got -1.0"),
    (dict(bogus=1), TypeError, "SimDataset: unexpected keyword argument(s) ['bogus']"),
    (dict(control=np.full((4, 10, 1), 1 + 2j)), TypeError,
     "control: expected real numbers, got a complex128 array"),
    # not one trajectory fits: the advice is about nstep, not about nbatch
    (dict(nstep=10**10), ValueError, "nstep: a batch of 4 trajectories of 10000000000 steps "
                                     "needs"),
]


@pytest.mark.parametrize("kwargs,error,message", CASES, ids=[c[2][:40] for c in CASES])
def test_bad_argument_message(kwargs, error, message):
    threads = threading.active_count()
    with pytest.raises(error, match=re.escape(message)):
        make(**kwargs)
    assert threading.active_count() == threads  # nothing was started


def test_model_errors():
    with pytest.raises(ValueError, match=re.escape("model: expected an MJCF/MJB path")):
        make("no/such/file.xml")
    with pytest.raises(TypeError, match="model: expected an MJCF/MJB path, an XML string, an "
                                        "MjModel or an MjSpec, got int"):
        make(3)
    with pytest.raises(ValueError, match="model: XML string failed to compile"):
        make("<mujoco><worldbody><body><joint type='nope'/></body></worldbody></mujoco>")


def test_models_of_different_sizes(rich_model):
    other = simloader.load_model("cartpole")
    with pytest.raises(ValueError, match=re.escape(
            "randomize[1]: models must have identical sizes; nq is 2, expected 9")):
        make(rich_model, nbatch=2, randomize=[rich_model, other])


def test_model_forms_are_equivalent(tmp_path):
    path = simloader.builtin_path("cartpole")
    xml = path.read_text()
    forms = [str(path), path, xml, mujoco.MjModel.from_xml_string(xml),
             mujoco.MjSpec.from_string(xml), "cartpole"]
    states = [next(iter(make(f, nthread=1, initial_state="hanging")))["state"] for f in forms]
    for s in states[1:]:
        assert np.array_equal(s.numpy(), states[0].numpy())
