"""Every Python block of the README runs as written; an endless stream gets a bounded variant
here (2 batches), not in the README. The CI script runs exactly the README's test command."""

import pathlib
import re

import pytest

import simloader

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def python_blocks():
    """(id, code) of each ```python block, named after its section and position."""
    out, section = [], "top"
    for part in re.split(r"(^## .*$)", README, flags=re.M):
        if part.startswith("## "):
            section = re.sub(r"\W+", "-", part[3:].strip().lower()).strip("-")
            continue
        for i, code in enumerate(re.findall(r"^```python\n(.*?)^```", part, re.S | re.M)):
            out.append((f"{section}-{i}", code))
    return out


BLOCKS = python_blocks()


class Bounded(simloader.SimDataset):
    """SimDataset whose endless streams end after 2 batches."""

    def __init__(self, *args, num_batches=None, **kwargs):
        super().__init__(*args, num_batches=2 if num_batches is None else num_batches, **kwargs)


def test_the_readme_has_python_blocks():
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize("code", [c for _, c in BLOCKS], ids=[i for i, _ in BLOCKS])
def test_readme_block_runs_as_written(code, monkeypatch):
    monkeypatch.setattr(simloader, "SimDataset", Bounded)
    exec(compile(code, "README.md", "exec"), {"__name__": "__main__"})


def test_ci_runs_exactly_the_readmes_test_command():
    command = next(line for line in README.splitlines()
                   if line.startswith("python3 -m pip") and "pytest" in line)
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert ci[-1] == command
