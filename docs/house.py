"""Draws simloader's modules as a house: each module a room on its floor, imports as arrows.

A module's floor is one above the highest module it imports at load time (imports inside
functions, made when first needed, are drawn dashed and do not raise a floor), so every solid
arrow points down. `docs/_static/house.png` on the contributors page is its output:

    python docs/house.py                 # writes docs/_static/house.png, prints the floors
    python docs/house.py --check         # only checks: no import circle, no arrow up

The same graph is what `tests/test_house.py` checks.
"""

from __future__ import annotations

import argparse
import ast
import pathlib
import sys
from collections import defaultdict

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "simloader"


def module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: pathlib.Path, modules: set[str]) -> tuple[set[str], set[str]]:
    """(modules of simloader imported at load time, those imported inside functions)."""
    tree = ast.parse(path.read_text())
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rsplit(".", 1)[0]
    top, lazy = set(), set()

    def targets(node: ast.AST) -> set[str]:
        out = set()
        if isinstance(node, ast.Import):
            out = {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1]
                                + ([node.module] if node.module else []))
            out = {f"{base}.{a.name}" for a in node.names} | {base}
        # the deepest simloader module each name is (a function imported from a module is
        # that module)
        found = set()
        for name in out:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name and name != here:
                found.add(name)
        return found

    def visit(node: ast.AST, nested: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                (lazy if inside else top).update(targets(child))
            visit(child, inside)

    visit(tree, False)
    return top, lazy - top


def graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """({module: modules it imports at load time}, {module: those it imports lazily})."""
    paths = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
    modules = set(paths)
    top, lazy = {}, {}
    for name, path in paths.items():
        top[name], lazy[name] = imports(path, modules)
    # a package's __init__ imported for a submodule is not an edge back up
    for name in top:
        top[name] = {m for m in top[name] if not name.startswith(m + ".")}
        lazy[name] = {m for m in lazy[name] if not name.startswith(m + ".")}
    return top, lazy


def floors(top: dict[str, set[str]]) -> dict[str, int]:
    """Each module's floor: 0 for one importing no other module of simloader at load time.

    Raises:
      ValueError: the load-time imports make a circle (naming it).
    """
    floor: dict[str, int] = {}
    visiting: list[str] = []

    def place(name: str) -> int:
        if name in floor:
            return floor[name]
        if name in visiting:
            circle = visiting[visiting.index(name):] + [name]
            raise ValueError(f"import circle: {' -> '.join(circle)}")
        visiting.append(name)
        floor[name] = 1 + max((place(m) for m in top[name]), default=-1)
        visiting.pop()
        return floor[name]

    for name in sorted(top):
        place(name)
    return floor


def draw(top: dict[str, set[str]], lazy: dict[str, set[str]], floor: dict[str, int],
         out: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # packages that are only a docstring (an engine's folder) are not rooms of their own
    used = {t for targets in (*top.values(), *lazy.values()) for t in targets}
    floor = {n: f for n, f in floor.items() if top[n] or lazy[n] or n in used}
    rows = defaultdict(list)
    for name, f in floor.items():
        rows[f].append(name)
    width = max(len(r) for r in rows.values())
    fig, ax = plt.subplots(figsize=(20, 0.95 * (len(rows) + 1)))
    where = {}
    order = ("", "store", "backends", "backends.cpu", "backends.mjx", "backends.warp", "tools")

    def group(name: str) -> int:
        inner = name.removeprefix("simloader").lstrip(".").rpartition(".")[0]
        return max((i for i, g in enumerate(order) if inner.startswith(g)), default=0)

    for f, names in rows.items():
        names.sort(key=lambda n: (group(n), n))
        for i, name in enumerate(names):
            where[name] = ((i + 0.5) * width / len(names), f)
    for kind, edges, style in (("lazy", lazy, (0, (2, 3))), ("load", top, "-")):
        for name, targets in edges.items():
            for t in targets & where.keys() if name in where else ():
                (x0, y0), (x1, y1) = where[name], where[t]
                ax.annotate("", xy=(x1, y1 + 0.18), xytext=(x0, y0 - 0.18),
                            arrowprops=dict(arrowstyle="->", linestyle=style, lw=0.6,
                                            color="#b45f06" if kind == "lazy" else "0.35",
                                            alpha=0.35))
    colours = {"backends": "#cfe2f3", "store": "#d9ead3", "tools": "#fce5cd"}
    for name, (x, y) in where.items():
        label = name.removeprefix("simloader.").replace("backends.", "b.")
        part = name.split(".")[1] if name.count(".") else ""
        ax.text(x, y, label, ha="center", va="center", fontsize=8.5,
                bbox=dict(boxstyle="round", fc=colours.get(part, "#eeeeee"), ec="0.4", lw=0.5))
    ax.set_yticks(sorted(rows))
    ax.set_yticklabels([f"floor {f}" for f in sorted(rows)])
    ax.set_xticks([])
    ax.set_xlim(0, width)
    ax.set_ylim(-0.7, max(rows) + 0.7)
    for side in ("top", "right", "bottom"):
        ax.spines[side].set_visible(False)
    ax.set_title(f"simloader: {len(floor)} modules on {len(rows)} floors. Grey arrows: imports "
                 f"at load time (all point down); orange dashed: imports when first needed. "
                 f"Blue: engines (b. = backends.), green: store, orange: tools", fontsize=11)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--check", action="store_true", help="only check; draw nothing")
    p.add_argument("--out", type=pathlib.Path, default=ROOT / "docs" / "_static" / "house.png")
    args = p.parse_args()
    top, lazy = graph()
    floor = floors(top)
    for f in sorted(set(floor.values()), reverse=True):
        print(f"floor {f}: " + ", ".join(sorted(n.removeprefix("simloader.")
                                               for n in floor if floor[n] == f)))
    if not args.check:
        draw(top, lazy, floor, args.out)
        print(f"wrote {args.out.relative_to(ROOT)}", file=sys.stderr)


if __name__ == "__main__":
    main()
