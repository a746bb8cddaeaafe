"""The `simloader` command's entry point: `--version` answers before anything heavy loads
(torch and MuJoCo take about 2 s to import); everything else is `simloader.cli`."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv == ["--version"]:
        import simloader  # light: its public names load on first use
        print(f"simloader {simloader.__version__}")
        return
    from simloader import cli
    cli.main(argv)
