"""Small audit fixes: randomized parameters' columns named (describe, `simloader info`,
`batch.view`), the policy version across replaced parameters, bytes devices refused, and
`simloader write --out` checked up front."""

import os

import pytest
import torch

import simloader
from simloader import cli
from simloader import policy as sp
from simloader import randomize as dr

FRICTION = dr.set("geom_friction", dr.Uniform(0.3, 1.2), on=["floor", "cart"])
PARAMS = [dr.scale("body_mass", dr.Uniform(0.5, 2.0), on="pole"),
          dr.scale("body_mass", dr.Uniform(0.5, 2.0), name="mass"),  # every body
          FRICTION,
          dr.set("geom_rgba", dr.Uniform(0.2, 1.0), on="pole", index=[0, 2])]
FRICTION_COLUMNS = "floor[0], floor[1], floor[2], cart[0], cart[1], cart[2]"


def make(**kwargs):
    return simloader.SimDataset("cartpole", backend="cpu", nbatch=3, nstep=2, nthread=1,
                                num_batches=1, **kwargs)


# -- 1. the columns of each randomized parameter are named --------------------------------------

def test_describe_names_the_columns_of_each_randomized_parameter():
    text = make(randomize=PARAMS).describe()
    assert "  body_mass[pole] (3, 1): columns pole\n" in text
    assert "  mass (3, 3): columns world, cart, pole\n" in text
    assert f"  geom_friction[floor,cart] (3, 6): columns {FRICTION_COLUMNS}\n" in text
    assert "  geom_rgba[pole] (3, 2): columns pole[0], pole[2]\n" in text


def test_info_names_the_columns_of_randomized_parameters(capsys):
    cli.main(["info", "cartpole", "--randomize", "body_mass", "--randomize",
              "geom_friction:floor,cart"])
    out = capsys.readouterr().out
    assert "  body_mass (nbatch, 3): columns world, cart, pole\n" in out
    assert f"  geom_friction[floor,cart] (nbatch, 6): columns {FRICTION_COLUMNS}\n" in out
    # an unknown object is a one-line usage error with the names there are
    with pytest.raises(SystemExit) as e:
        cli.main(["info", "cartpole", "--randomize", "body_mass:pol"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "did you mean 'pole'" in err, err


def test_batch_view_finds_a_randomized_parameter_by_column_name():
    batch = next(iter(make(randomize=PARAMS)))
    mass, friction = batch["params"]["mass"], batch["params"]["geom_friction[floor,cart]"]
    assert torch.equal(batch.view("mass", "world"), mass[:, 0:1])
    assert torch.equal(batch.view("mass", "pole"), mass[:, 2:3])
    assert torch.equal(batch.view("params/body_mass[pole]", "pole"),
                       batch["params"]["body_mass[pole]"])
    # an object's columns, or one component of it
    assert torch.equal(batch.view("geom_friction[floor,cart]", "cart"), friction[:, 3:6])
    view = batch.view("geom_friction[floor,cart]", "cart[1]")
    assert torch.equal(view, friction[:, 4:5])
    assert view.data_ptr() == friction[:, 4].data_ptr()  # a view, not a copy
    assert torch.equal(batch.view("geom_rgba[pole]", "pole[2]"),
                       batch["params"]["geom_rgba[pole]"][:, 1:2])
    with pytest.raises(KeyError, match=r"no object 'pol' \(did you mean 'pole'\?\); its "
                                       r"objects: \['world', 'cart', 'pole'\]"):
        batch.view("mass", "pol")


# -- 2. the policy version moves when a parameter is replaced -----------------------------------

def test_policy_version_moves_when_a_parameter_is_replaced():
    torch.manual_seed(0)
    net = torch.nn.Linear(2, 1)
    with torch.no_grad():
        for _ in range(3):
            net.weight.add_(1.0)  # in-place updates: the counters move
    seen = [sp.version(net)]
    for k in range(3):
        net.weight = torch.nn.Parameter(torch.full((1, 2), float(k)))  # counter back at 0
        seen.append(sp.version(net))
        assert sp.version(net) == seen[-1]  # stable while nothing changes
        with torch.no_grad():
            net.bias.add_(1.0)
        seen.append(sp.version(net))
    assert all(a < b for a, b in zip(seen, seen[1:])), seen
    # a batch's snapshot copies the new object's weights, under the version it names
    snapshot = sp.Snapshot(net)
    frozen, version = snapshot.take()
    assert version == sp.version(net) and torch.equal(frozen.weight, net.weight)
    net.weight = torch.nn.Parameter(torch.full((1, 2), 7.0))
    frozen, later = snapshot.take()
    assert later > version and torch.equal(frozen.weight, torch.full((1, 2), 7.0))


# -- 3. a device given as bytes is refused --------------------------------------------------

def test_sim_device_as_bytes_is_refused():
    with pytest.raises(ValueError, match=r"sim_device: expected 'cpu', 'cuda' or 'cuda:N'"
                                         r".*got bytes b'cpu'"):
        make(sim_device=b"cpu")


# -- 4. `simloader write --out` -------------------------------------------------------------

WRITE = ["write", "cartpole", "--backend", "cpu", "--nbatch", "2", "--nstep", "2",
         "--batches", "1"]


def _usage_error(capsys, argv):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert err.startswith("simloader write: error: "), err
    return err


def test_write_refuses_an_existing_file_or_empty_out(capsys, tmp_path, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("simloader.write called")
    monkeypatch.setattr(cli.simloader, "write", never)
    (tmp_path / "file").write_text("x")
    err = _usage_error(capsys, [*WRITE, "--out", str(tmp_path / "file")])
    assert "--out: expected a folder" in err and "an existing file" in err
    err = _usage_error(capsys, [*WRITE, "--out", str(tmp_path / "file" / "store")])
    assert "--out" in err and "below the existing file" in err
    err = _usage_error(capsys, [*WRITE, "--out", ""])
    assert "--out: expected a folder" in err and "empty path ''" in err
    assert (tmp_path / "file").read_text() == "x"


def test_write_refuses_a_read_only_out(capsys, tmp_path, monkeypatch):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    if os.geteuid() == 0:  # root writes into read-only folders: os.access says what a user sees
        access = os.access
        monkeypatch.setattr(os, "access", lambda path, mode: (
            not mode & os.W_OK if os.fspath(path) == str(folder) else access(path, mode)))
    try:
        err = _usage_error(capsys, [*WRITE, "--out", str(folder / "a" / "store")])
    finally:
        folder.chmod(0o755)
    assert "--out" in err and "read-only" in err and str(folder) in err


def test_write_argument_refusals_are_one_line(capsys, tmp_path, monkeypatch):
    def refuse(dataset, path, **kwargs):
        raise ValueError(f"write: path: expected an empty folder or a simloader store, got "
                         f"{path!r}, a folder\nof other files")
    monkeypatch.setattr(cli.simloader, "write", refuse)
    err = _usage_error(capsys, [*WRITE, "--out", str(tmp_path / "store")])
    assert "write: path: expected an empty folder" in err and "folder of other files" in err
