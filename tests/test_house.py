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
    # baselines `simloader bench` compares with (bench/raw.py) drive MJX themselves
    top, lazy = house.graph()
    reaching = sorted((m, t) for g in (top, lazy) for m, targets in g.items() for t in targets
                      for e in ENGINES if (t == e or t.startswith(e + "."))
                      and not (m == e or m.startswith(e + ".")))
    assert reaching == [("simloader.bench.raw", "simloader.backends.mjx.runtime")]


def test_no_circle_through_lazy_imports_either():
    # an import inside a function is still an arrow: a module that imports one that imports
    # it back, at load time or later, is one concern split in two
    top, lazy = house.graph()
    both = {m: set(top.get(m, ())) | set(lazy.get(m, ())) for m in set(top) | set(lazy)}
    house.floors(both)  # raises on a circle, naming it


# engine words as values: only the registry and the engines' folders hold them. bench/ is
# `simloader bench`'s raw baselines, which drive each engine's raw library by name (the CLI's
# `bench --backends` choices are those baselines)
ENGINE_WORDS = {"cpu", "mjx", "warp", "rollout"}
ALLOWED = ("simloader/backends/", "simloader/bench/")


def _engine_words(path):
    """(line, word) of every engine word used as a value in `path`'s code: a string equal to
    "mjx", "warp" or "rollout" anywhere, "cpu" where compared with or given as a backend."""
    import ast
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            names = ast.unparse(node).lower()
            for side in sides:
                if isinstance(side, ast.Constant) and side.value == "cpu" and "backend" in names \
                        and "device" not in names:
                    found.append((node.lineno, "cpu"))
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                node.value in ENGINE_WORDS - {"cpu"}:
            found.append((node.lineno, node.value))
        if isinstance(node, ast.keyword) and node.arg == "backend" and \
                isinstance(node.value, ast.Constant) and node.value.value in ENGINE_WORDS:
            found.append((node.lineno, node.value.value))
    return found


def test_no_engine_name_outside_the_registry_and_the_engines():
    package = ROOT / "simloader"
    words = {str(p.relative_to(ROOT)): _engine_words(p) for p in package.rglob("*.py")
             if not str(p.relative_to(ROOT)).startswith(ALLOWED)}
    # the CLI's `bench --backends`: the raw baselines tools/bench.py times
    bench = [n for n, line in enumerate((package / "cli.py").read_text().splitlines(), 1)
             if "--backends" in line]
    words["simloader/cli.py"] = [(n, w) for n, w in words["simloader/cli.py"]
                                 if n not in bench]
    assert {p: w for p, w in words.items() if w} == {}


def test_the_engine_word_check_finds_them():
    import tempfile
    with tempfile.TemporaryDirectory() as folder:
        code = pathlib.Path(folder) / "m.py"
        code.write_text("def f(c):\n    if c.backend == 'cpu':\n        return 'mjx'\n"
                        "    return g(backend='warp', device='cpu')\n")
        assert sorted(_engine_words(code)) == [(2, "cpu"), (3, "mjx"), (4, "warp"), (4, "warp")]
