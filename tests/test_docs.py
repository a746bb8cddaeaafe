"""The README and the docs pages, as a user meets them.

Every ```python block of README.md and of docs/*.md runs as written; an endless stream gets
a bounded variant here (2 batches), not in the pages. A block whose first line is
`# needs a CUDA GPU` is marked `gpu` (run with `-m gpu` on a GPU machine). The CI script runs
exactly the README's test command, the docs site builds offline with warnings as errors and
every cross-reference resolved, and every relative link of the pages, and every local link and
anchor of the built site, points to something that exists."""

import pathlib
import re
import subprocess
import sys
import urllib.parse

import pytest

import simloader

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
GPU_LINE = "# needs a CUDA GPU"


def python_blocks(path):
    """(id, code) of each ```python block of one page, named after the page, its section and
    the block's position there (a `#` line inside a block is code, not a heading)."""
    out, section, index, block, fence = [], "top", 0, None, None
    for line in path.read_text().splitlines(keepends=True):
        if block is not None:
            if line.rstrip() == "```":
                out.append((f"{path.stem.lower()}:{section}-{index}", "".join(block)))
                index, block = index + 1, None
            else:
                block.append(line)
        elif fence is not None:
            fence = None if line.rstrip() == fence else fence
        elif line.rstrip() == "```python":
            block = []
        elif line.startswith("```"):
            fence = re.match(r"`+", line).group()
        elif re.match(r"##? ", line):
            section, index = re.sub(r"\W+", "-", line.lstrip("#").strip().lower()).strip("-"), 0
    return out


# the tutorial's blocks build on each other: tests/test_tutorial.py runs them in order
SEQUENTIAL = {"tutorial.md"}
BLOCKS = [block for path in PAGES if path.name not in SEQUENTIAL for block in python_blocks(path)]


def _param(block_id, code):
    marks = [pytest.mark.gpu] if code.lstrip().startswith(GPU_LINE) else []
    return pytest.param(code, id=block_id, marks=marks)


class Bounded(simloader.SimDataset):
    """SimDataset whose endless streams end after 2 batches."""

    def __init__(self, *args, num_batches=None, **kwargs):
        super().__init__(*args, num_batches=2 if num_batches is None else num_batches, **kwargs)


def test_the_pages_have_python_blocks():
    assert len(python_blocks(ROOT / "README.md")) >= 2
    assert len(BLOCKS) >= 12
    gpu = [i for i, code in BLOCKS if code.lstrip().startswith(GPU_LINE)]
    assert len(gpu) <= 3, f"keep the blocks that need a GPU few: {gpu}"


@pytest.mark.parametrize("code", [_param(i, c) for i, c in BLOCKS])
def test_block_runs_as_written(code, monkeypatch):
    if code.lstrip().startswith(GPU_LINE):
        torch = pytest.importorskip("torch")
        if not torch.cuda.is_available():
            pytest.skip("needs a CUDA GPU")
    monkeypatch.setattr(simloader, "SimDataset", Bounded)
    exec(compile(code, "docs", "exec"), {"__name__": "__main__"})


def test_ci_runs_exactly_the_readmes_test_command():
    command = next(line for line in README.splitlines()
                   if line.startswith("python3 -m pip") and "pytest" in line)
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert ci[-1] == command


@pytest.fixture(scope="module")
def built_html(tmp_path_factory):
    """The site, built once for the tests that read it: offline, every warning an error (`-W`),
    every cross-reference checked (`-n`); the build's output, for the test that asserts it."""
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    out = tmp_path_factory.mktemp("docs")
    run = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "-n", "--keep-going", "-q", "-b", "html",
         "-d", str(out / "doctrees"), str(ROOT / "docs"), str(out / "html")],
        capture_output=True, text=True, timeout=300, cwd=ROOT)
    return run, out / "html"


def test_the_docs_build_offline_without_warnings(built_html):
    run, html = built_html
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-4000:]
    assert (html / "index.html").exists()
    assert (html / "api.html").exists()


HREF = re.compile(r"""\shref=["']([^"']+)["']""")
ID = re.compile(r"""\sid=["']([^"']+)["']""")


def test_the_built_site_has_no_broken_local_links(built_html):
    """Every link of the built pages to a local page, and to an anchor there, arrives: a
    page that exists, an id that it holds (Markdown links, autodoc cross-references, the
    "[source]" pages, a docstring's slip that links to a `#id1` nowhere)."""
    run, html = built_html
    if not (html / "index.html").exists():
        pytest.skip("the site did not build")
    ids, broken = {}, []
    for page in sorted(html.rglob("*.html")):
        for href in HREF.findall(page.read_text()):
            if re.match(r"[a-z][a-z0-9+.-]*:", href):
                continue  # http:, mailto:, ...
            path, _, anchor = href.partition("#")
            path = urllib.parse.unquote(path.partition("?")[0])  # style.css?v=...
            target = (page.parent / path).resolve() if path else page
            if not target.exists():
                broken.append(f"{page.relative_to(html)}: {href}")
            elif anchor and target.suffix == ".html":
                if target not in ids:
                    ids[target] = set(ID.findall(target.read_text()))
                if anchor not in ids[target]:
                    broken.append(f"{page.relative_to(html)}: {href}")
    assert not broken, "broken links in the built site:\n" + "\n".join(broken)


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
DIRECTIVE = re.compile(r"^(`{3,})\{(?:figure|image|include)\}\s+(\S+)")


def relative_links(path):
    """Targets of the page's Markdown links and images, and of its figure, image and include
    directives, that are paths in this repository (not URLs, not anchors within the page);
    code blocks and inline code are not links."""
    targets, fence = [], None
    for line in path.read_text().splitlines():
        if fence is not None:
            fence = None if line.strip() == fence else fence
            continue
        directive = DIRECTIVE.match(line)
        if directive:
            targets.append(directive.group(2))
        if line.startswith("```"):
            fence = re.match(r"`+", line).group()
            continue
        targets += LINK.findall(re.sub(r"`[^`]*`", "", line))
    out = []
    for target in targets:
        target = target.split("#")[0]
        if target and not re.match(r"[a-z][a-z0-9+.-]*:", target):
            out.append(target)
    return out


def _exists(page, target):
    """A link's target exists; `results/NAME.md` of a docs page is the page the build makes of
    `benchmarks/results/NAME.md` (docs/conf.py), there whether the site was built or not."""
    if page.parent.name == "docs" and target.startswith("results/"):
        return (ROOT / "benchmarks" / target).exists()
    return (page.parent / target).exists()


@pytest.mark.parametrize("path", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_relative_links_point_to_files(path):
    missing = [t for t in relative_links(path) if not _exists(path, t)]
    assert not missing, f"{path.relative_to(ROOT)} links to missing files: {missing}"


def test_the_link_check_sees_links():
    assert "docs/speed.md" in relative_links(ROOT / "README.md")
    assert any(t.endswith(".png") for t in relative_links(ROOT / "docs" / "speed.md"))


# -- the shell blocks ----------------------------------------------------------------------

def bash_commands(path):
    """(page:line, command) of every command of a page's ```bash blocks (continuation lines
    joined, `&&` chains split, comments dropped)."""
    out, block, start = [], None, 0
    lines = path.read_text().splitlines()
    for number, line in enumerate(lines, 1):
        if block is None:
            if line.rstrip() == "```bash":
                block, start = [], number
            continue
        if line.rstrip() == "```":
            text = "\n".join(block).replace("\\\n", " ")
            for k, command in enumerate(text.splitlines()):
                command = command.split("  #")[0].strip()
                if command and not command.startswith("#"):
                    out += [(f"{path.name}:{start + k + 1}", part.strip())
                            for part in command.split("&&")]
            block = None
        else:
            block.append(line)
    return out


COMMANDS = [c for path in PAGES for c in bash_commands(path)]
# what a test cannot run here, and why: everything else is run
NOT_HERE = {
    "python3 -m pip": "installs (this machine reaches no index; CI installs as the README says)",
    "pip install": "installs (as above)",
    "python3 -m venv": "makes a virtual environment (the suite runs in one already)",
    ". .venv/bin/activate": "activates it (as above)",
    "python3 -m pytest": "runs the suite (it is the suite)",
    "sphinx-build": "builds the docs (test_the_docs_build_offline_without_warnings does)",
    "torchrun": "needs GPUs (test_ddp_example_under_torchrun runs it on CPU ranks)",
}
# the small sizes the commands run at here (their full sizes take minutes on 2 cores)
SMALL = {"quickstart": ["--backend", "cpu", "--nbatch", "8", "--nstep", "5", "--batches", "2"]}


RUN = [(w, c) for w, c in COMMANDS if not c.startswith(tuple(NOT_HERE))]


@pytest.mark.parametrize("where, command", RUN, ids=[w for w, _ in RUN])
def test_shell_command_runs_as_written(where, command, capsys, monkeypatch):
    import shlex
    from simloader import cli
    argv = shlex.split(command)
    monkeypatch.chdir(ROOT)
    cli.main(argv[1:] + SMALL.get(argv[1], []))
    assert capsys.readouterr().out.strip(), f"{where}: {command!r} printed nothing"


def test_every_shell_command_is_run_or_says_why_not():
    """A new command in a page's bash block is run by the test above (a `simloader`
    command), or its kind is in NOT_HERE with the reason."""
    assert any(c == "simloader quickstart" for _, c in RUN)
    assert any(c.startswith("simloader info") for _, c in RUN)
    other = [(w, c) for w, c in RUN if not c.startswith("simloader ")]
    assert not other, f"shell commands the docs test neither runs nor explains: {other}"


def test_the_results_pages_touch_only_what_the_build_made(tmp_path):
    """docs/conf.py makes a page per cited results file in docs/results/ and removes the
    pages it made that nothing cites any more: never a file of someone else there, never
    through a link."""
    import runpy
    import shutil
    docs = tmp_path / "docs"
    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "benchmarks" / "results" / "x.md").write_text("# x\n")
    docs.mkdir()
    shutil.copy(ROOT / "docs" / "conf.py", docs / "conf.py")
    (docs / "page.md").write_text("see [x](results/x.md)\n")
    (docs / "results").mkdir()
    mine = docs / "results" / "mine.md"
    mine.write_text("# my own notes\n")
    old = docs / "results" / "old.md"
    old.write_text("```{include} ../../benchmarks/results/old.md\n:relative-images:\n```\n")
    runpy.run_path(str(docs / "conf.py"))
    assert (docs / "results" / "x.md").read_text().startswith("```{include} ../../benchmarks")
    assert mine.read_text() == "# my own notes\n" and not old.exists()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (docs / "results" / "x.md").unlink()
    (docs / "results" / "x.md").symlink_to(elsewhere / "target.md")
    with pytest.raises(RuntimeError, match="is a link"):
        runpy.run_path(str(docs / "conf.py"))
    assert not (elsewhere / "target.md").exists()
