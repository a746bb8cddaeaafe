"""Models by name: the built-in ones, and Gymnasium's MuJoCo models where gymnasium is
installed; `describe()` and errors say where a name resolved from and which names exist."""

import mujoco
import pytest

import simloader
from simloader import models


def test_builtin_models_load_and_say_where_they_come_from():
    assert {"cartpole", "humanoid"} <= set(simloader.builtin_models())
    humanoid = simloader.load_model("humanoid")  # the DeepMind Control Suite humanoid
    assert humanoid.nu == 21 and humanoid.body("head").id > 0
    assert simloader.describe("humanoid").splitlines()[0] == (
        f"model: 'humanoid', built-in: {simloader.builtin_path('humanoid')}")


def test_unknown_name_lists_the_names_that_exist():
    with pytest.raises(ValueError, match=r"model: .* got 'humanoids' \(no such file or model\); "
                                         r"model names are \[.*'cartpole', 'humanoid'"):
        simloader.load_model("humanoids")


def test_without_gymnasium_the_error_says_how_to_get_its_models(monkeypatch):
    monkeypatch.setattr(models, "_gymnasium_assets", lambda: None)
    with pytest.raises(ValueError, match=r"once gymnasium is installed: python3 -m pip install "
                                         r"gymnasium"):
        simloader.load_model("hopper")


def test_gymnasium_models_by_name():
    gymnasium = pytest.importorskip("gymnasium")
    named = simloader.named_models()
    assert {"gymnasium/hopper", "gymnasium/half_cheetah", "gymnasium/ant"} <= set(named)
    assert simloader.load_model("hopper").nq == simloader.load_model("gymnasium/hopper").nq == 6
    # a built-in name stays built-in; Gymnasium's humanoid has its prefix
    assert simloader.load_model("humanoid").nu == 21
    assert simloader.load_model("gymnasium/humanoid").nu == 17
    ds = simloader.SimDataset("gymnasium/half_cheetah", backend="cpu", nbatch=2, nstep=5,
                              control=simloader.controls.Uniform(), num_batches=1, nthread=1)
    first = ds.describe().splitlines()[0]
    assert first.startswith(f"model: 'gymnasium/half_cheetah', gymnasium "
                            f"{gymnasium.__version__}: ") and first.endswith("half_cheetah.xml")
    batch = next(iter(ds))
    assert batch["state"].shape == (2, 5, mujoco.mj_stateSize(ds.model,
                                                              simloader.layout.FULLPHYSICS))
    assert not batch["diverged"].any()
    with pytest.raises(ValueError, match=r"'gymnasium/hopper'"):
        simloader.load_model("gymnasium/hoper")


def test_a_built_in_name_is_never_shadowed_by_a_file(tmp_path, monkeypatch):
    """One rule: a name is the built-in model (a warning names the file it did not load);
    a file is loaded by a path or a suffix."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cartpole").write_text('<mujoco><worldbody><body><joint type="slide"/>'
                                       '<geom size=".1"/></body></worldbody></mujoco>')
    with pytest.warns(UserWarning, match=r"'cartpole' is a built-in model name.*pass "
                                         r"'\./cartpole' to load the file"):
        built_in = simloader.load_model("cartpole")
    assert built_in.nq == 2
    assert simloader.load_model("./cartpole").nq == 1
    assert simloader.load_model(str(tmp_path / "cartpole")).nq == 1
