"""Known faults of the simulators: which versions, models and engines each one touches, the
warning at construction, `describe()`, the CLI's `info`, and what a store records and says.

The fault of the table today, mujoco#3767, is in MuJoCo 4.0.0 and fixed in 4.0.1. The table's
own checks pass the versions explicitly; the checks of what a dataset does at construction
expect the warning exactly where the installed MuJoCo has the fault, and none elsewhere."""

import warnings

import mujoco
import pytest

import simloader
from simloader import cli, known_faults

FAULT = known_faults.FAULTS[0]
AFFECTED = {"mujoco": "4.0.0"}
FIXED = {"mujoco": "4.0.1"}
# whether the MuJoCo installed here has the fault (4.0.0: yes)
HERE = FAULT.affects(known_faults.installed()["mujoco"])
only_where_affected = pytest.mark.skipif(not HERE, reason="the installed MuJoCo has no "
                                                          "known fault")


def chain(n, option=""):
    """A chain of `n` hinged capsules (nv = n) above a floor, with `option` in <option>."""
    links = "".join('<body pos="0.1 0 0"><joint type="hinge" axis="0 1 0" range="-30 30"/>'
                    '<geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.02"/>'
                    for _ in range(n))
    return (f'<mujoco><option {option}/><worldbody><geom type="plane" size="5 5 .1"/>'
            f'<body pos="0 0 0.5"><geom size="0.05"/>{links}{"</body>" * n}</body>'
            f'</worldbody></mujoco>')


def model(xml):
    return mujoco.MjModel.from_xml_string(xml)


def dataset(xml):
    return simloader.SimDataset(xml, backend="cpu", nbatch=2, nstep=2, nthread=1)


@pytest.fixture
def fresh(monkeypatch):
    # the faults warned of so far in this process: none (each test sees its own first warning)
    monkeypatch.setattr(known_faults, "_WARNED", set())


def test_a_sparse_jacobian_meets_the_fault_on_mujoco_4_0_0():
    assert known_faults.applying(model(chain(3, 'jacobian="sparse"')), "cpu",
                                 AFFECTED) == [FAULT]


def test_a_dense_jacobian_and_auto_below_nv_60_do_not():
    for xml in (chain(3, 'jacobian="dense"'), chain(80, 'jacobian="dense"'), chain(59)):
        assert known_faults.applying(model(xml), "cpu", AFFECTED) == []


def test_auto_from_nv_60_is_sparse_and_meets_it():
    m = model(chain(60))
    assert m.opt.jacobian == mujoco.mjtJacobian.mjJAC_AUTO and m.nv == 60
    assert known_faults.applying(m, "cpu", AFFECTED) == [FAULT]
    assert FAULT.applies(m) == 'solver="Newton", jacobian="auto" with nv=60: sparse'


def test_only_the_newton_solver_meets_it():
    # the release notes: a wrong Hessian factor of the Newton solver (CG and PGS factor none)
    for solver in ("CG", "PGS"):
        m = model(chain(3, f'jacobian="sparse" solver="{solver}"'))
        assert known_faults.applying(m, "cpu", AFFECTED) == []


def test_only_mujoco_c_runs_it():
    # MJX and MuJoCo Warp solve with their own code
    m = model(chain(3, 'jacobian="sparse"'))
    assert known_faults.applying(m, "mjx", AFFECTED) == []
    assert known_faults.applying(m, "warp", AFFECTED) == []
    assert known_faults.applying(m, None, AFFECTED) == [FAULT]


def test_the_versions_it_is_in():
    assert FAULT.affects("4.0.0")
    for version in ("4.0.1", "4.1.0", "5.0.0", "3.17.0", None):
        assert not FAULT.affects(version), version
    m = model(chain(3, 'jacobian="sparse"'))
    assert known_faults.applying(m, "cpu", FIXED) == []
    with pytest.raises(ValueError, match=r"version: expected one starting with release "
                                         r"numbers such as '4.0.1', got 'main'"):
        FAULT.affects("main")


def test_the_fault_in_words_names_the_fix_and_the_setting_that_avoids_it():
    said = FAULT.said("4.0.0", model(chain(3, 'jacobian="sparse"')))
    assert said.startswith("mujoco#3767 (https://github.com/google-deepmind/mujoco/issues/3767"
                           "): mujoco 4.0.0 on backend='cpu': ")
    assert "(this model: solver=\"Newton\", jacobian=\"sparse\" with nv=3: sparse)" in said
    assert said.endswith("fixed in mujoco 4.0.1 (upgrade: python3 -m pip install "
                         "'mujoco>=4.0.1'), or avoid it with <option jacobian=\"dense\"/>")


@only_where_affected
def test_construction_warns_once_per_model(fresh):
    xml = chain(3, 'jacobian="sparse"')
    with pytest.warns(known_faults.KnownFaultWarning) as caught:
        dataset(xml)
        dataset(xml)  # compiled again: the same model, warned of already
        dataset(chain(4, 'jacobian="sparse"'))  # another model
    said = [w for w in caught if w.category is known_faults.KnownFaultWarning]
    assert len(said) == 2
    text = str(said[0].message)
    assert text.startswith("simloader: a known fault of the simulator applies to this model, "
                           "so its trajectories may be wrong: mujoco#3767")
    assert "fixed in mujoco 4.0.1" in text and '<option jacobian="dense"/>' in text
    assert said[0].filename == __file__  # the user's line


@only_where_affected
def test_construction_warns_for_auto_from_nv_60(fresh):
    with pytest.warns(known_faults.KnownFaultWarning, match="jacobian=\"auto\" with nv=60"):
        dataset(chain(60))


def test_construction_is_silent_where_the_fault_does_not_apply(fresh):
    xmls = [chain(3, 'jacobian="dense"'), chain(59)]
    if not HERE:  # a MuJoCo with the fault fixed: sparse models too
        xmls.append(chain(3, 'jacobian="sparse"'))
    with warnings.catch_warnings():
        warnings.simplefilter("error", known_faults.KnownFaultWarning)
        for xml in xmls:
            assert "known fault" not in dataset(xml).describe()


@only_where_affected
def test_describe_names_the_fault(fresh):
    with pytest.warns(known_faults.KnownFaultWarning):
        ds = dataset(chain(3, 'jacobian="sparse"'))
    last = ds.describe().splitlines()[-1]
    assert last == "known fault: " + FAULT.said(known_faults.installed()["mujoco"], ds.model)


def test_info_names_the_fault(tmp_path, capsys):
    path = tmp_path / "sparse.xml"
    path.write_text(chain(3, 'jacobian="sparse"'))
    cli.main(["info", str(path)])
    out = capsys.readouterr().out
    assert ("known fault: mujoco#3767" in out) == HERE
    cli.main(["info", "cartpole"])
    assert "known fault" not in capsys.readouterr().out


def test_recorded_names_the_faults_a_stream_meets(fresh):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", known_faults.KnownFaultWarning)
        sparse = dataset(chain(3, 'jacobian="sparse"'))
    assert known_faults.recorded(sparse) == (["mujoco#3767"] if HERE else [])
    assert known_faults.recorded(dataset(chain(3, 'jacobian="dense"'))) == []


def test_a_store_that_recorded_a_fault_is_flagged():
    said = known_faults.stored_warning({"versions": AFFECTED, "known_faults": ["mujoco#3767"]})
    assert said == ("the store was simulated under known fault(s) of the simulator, so its "
                    "trajectories may be wrong (write it again with the version that fixes "
                    "it, or with the model setting that avoids it): " + FAULT.said("4.0.0"))
    assert known_faults.stored_warning({"versions": AFFECTED, "known_faults": []}) is None
    newer = known_faults.stored_warning({"versions": AFFECTED, "known_faults": ["warp#1"]})
    assert newer.endswith(": warp#1 (unknown to this simloader: a newer one recorded it)")


def test_a_store_from_before_the_record_is_told_by_its_models():
    sparse, dense = model(chain(3, 'jacobian="sparse"')), model(chain(3, 'jacobian="dense"'))
    # the older spelling of the CPU engine, as stores of the time saved it
    root = {"versions": AFFECTED, "fingerprint": {"backend": "rollout"}}
    assert "mujoco#3767" in known_faults.stored_warning(root, models=lambda: [dense, sparse])
    assert known_faults.stored_warning(root, models=lambda: [dense]) is None
    kept_none = known_faults.stored_warning(root, models=lambda: None)
    assert kept_none.startswith("the store was simulated before simloader recorded the known "
                                "faults its model met")
    loads = []
    for other in ({"versions": FIXED, "fingerprint": {"backend": "cpu"}},
                  {"versions": AFFECTED, "fingerprint": {"backend": "warp"}}):
        # nothing to fear from these versions and engine: the models are not loaded
        assert known_faults.stored_warning(other, models=lambda: loads.append(1)) is None
    assert loads == []



@only_where_affected
def test_a_store_written_under_the_fault_says_so_in_its_description(tmp_path, fresh):
    with pytest.warns(known_faults.KnownFaultWarning):
        ds = simloader.SimDataset(chain(3, 'jacobian="sparse"'), backend="cpu", nbatch=2,
                                  nstep=2, nthread=1, num_batches=1)
    simloader.write(ds, str(tmp_path / "store"), batches=1, progress=False)
    with pytest.warns(known_faults.KnownFaultWarning, match=r"store: the store was simulated "
                                                          r"under known fault.*mujoco#3767"):
        stored = simloader.StoredDataset(tmp_path / "store")  # flagged when it is opened
    assert stored.info["known_faults"] == ["mujoco#3767"]
    fault, = [line for line in ds.describe().splitlines() if line.startswith("known fault")]
    assert stored.describe().splitlines()[-1] == fault
    assert fault.startswith("known fault: mujoco#3767")
