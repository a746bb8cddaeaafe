"""The house's rules, checked on the import graph of the package (`docs/house.py` draws it):
no import circle at load time, and every engine lives in its folder alone."""

import importlib.util
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("house", ROOT / "docs" / "house.py")
house = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(house)
ENGINES = ("simloader.backends.cpu", "simloader.backends.mjx", "simloader.backends.warp")


def test_no_import_circle_and_every_arrow_points_down():
    top, _ = house.graph()
    floor = house.floors(top)  # raises on a circle, naming it
    assert all(floor[t] < floor[m] for m, targets in top.items() for t in targets)
    assert "simloader.dataset" in floor and floor["simloader.layout"] == 0


def test_a_circle_is_named():
    try:
        house.floors({"a": {"b"}, "b": {"c"}, "c": {"a"}})
    except ValueError as e:
        assert "a -> b -> c -> a" in str(e)
    else:
        raise AssertionError("no circle found")


def test_every_engine_lives_in_its_folder_alone():
    # outside an engine's folder nothing imports its modules, at load time or later: the
    # registry names each engine's entry module as a string (backends.ENGINES). The raw
    # baselines `simloader bench` compares with (tools/) drive MJX themselves
    top, lazy = house.graph()
    reaching = sorted((m, t) for g in (top, lazy) for m, targets in g.items() for t in targets
                      for e in ENGINES if (t == e or t.startswith(e + "."))
                      and not (m == e or m.startswith(e + ".")))
    assert reaching == [("simloader.tools.bench", "simloader.backends.mjx.runtime")]
