"""Every example runs in its --quick mode (as a user would run it, in a fresh process)."""

import pathlib
import subprocess
import sys

import pytest

EXAMPLES = sorted((pathlib.Path(__file__).parents[1] / "examples").glob("*.py"))


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_quick(path, tmp_path, checkout_env):
    args = [sys.executable, str(path), "--quick"]
    if "--out" in path.read_text():
        args += ["--out", str(tmp_path / "plot.png")]
    if "--backend" in path.read_text():
        args += ["--backend", "cpu"]
    result = subprocess.run(args, capture_output=True, text=True, timeout=300, env=checkout_env(),
                            cwd=pathlib.Path(__file__).parents[1])
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-4000:]
    if "--out" in args:
        assert (tmp_path / "plot.png").stat().st_size > 10_000


def test_every_example_is_shown_in_the_docs():
    page = (pathlib.Path(__file__).parents[1] / "docs" / "examples.md").read_text()
    for path in EXAMPLES:
        assert f"```{{literalinclude}} ../examples/{path.name}" in page, (
            f"docs/examples.md does not show {path.name}: add its section under 'The scripts'")
