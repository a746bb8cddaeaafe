"""The `simloader` command line: `quickstart` (stream batches, print throughput), `write`
(simulate into a store), `info` (what the columns mean), `bench` (simloader next to the raw
simulators), `warmup` (compile ahead of time: JAX's persistent compilation cache and MuJoCo
Warp's kernel cache), `check` (an engine's physics against MuJoCo C's) and `video`
(trajectories of a store or a model, side by side)."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import time
from typing import Any

import mujoco
import torch
from tqdm import tqdm

import simloader
from simloader.store import StoreLocked, formats
from simloader import backends, cli_specs, known_faults, observe, threads

DEFAULT_MODEL = "cartpole"
# the registry's words, and its older spellings (still accepted; the library warns once)
BACKEND_CHOICES = backends.backends() + tuple(backends.OLD_BACKENDS)


def engines_here() -> list[str]:
    """The engines `bench` times by default: those that simulate on the CPU, and those that
    simulate on a GPU where their packages and a GPU are (MJX on JAX's CPU only when asked:
    `--backends mjx`)."""
    from simloader.backends import auto
    gpu = backends.on_devices()
    here = [name for name in backends.ENGINES if name not in gpu]
    if not backends.gpu_visible():
        return here
    can = auto.candidates()
    return here + [name for name in gpu if not can.get(name)]
DEFAULT_OUT = "simloader-results"


class ArgumentParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line on stderr (exit status 2): the usage is one
    `-h` away, and a new user reads the message rather than scrolling past a usage block."""

    def error(self, message: str) -> None:
        message = re.sub(r"\s*\n\s*", " ", str(message)).strip()
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} -h')\n")


class HelpFormatter(argparse.HelpFormatter):
    """Help that shows every option's default (where it has one and the help does not say it
    already)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "default" in text or default is None or default is False or default == [] or \
                default is argparse.SUPPRESS or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


# what the options without a help text of their own are
OPTION_HELP = {"--nbatch": "trajectories per batch", "--nstep": "steps per trajectory",
               "--batches": "batches in all", "--seed": "the seed all randomness derives from",
               "--format": "the store's format"}


def show_progress(args: argparse.Namespace) -> bool:
    """Progress bars: on a terminal, unless --quiet (none into a pipe or a file)."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


class BadArgument(Exception):
    """The library rejected a value that came from the command line."""


@contextlib.contextmanager
def from_arguments():
    """Wraps building the model/dataset from the arguments: the library's ValueError/TypeError
    there names the argument, what was expected and what was given, and becomes a usage error.
    Only the building: errors raised later while simulating keep their traceback."""
    try:
        yield
    except (ValueError, TypeError) as e:
        raise BadArgument(str(e)) from None


def positive_int(text: str) -> int:
    """An integer >= 1, for sizes and counts."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return value


def add_model_argument(parser: argparse.ArgumentParser) -> None:
    """The model, the same way in every subcommand: an optional positional argument."""
    parser.add_argument("model", nargs="?", default=None,
                        help=f"built-in model name or MJCF/MJB path (default: the built-in "
                             f"{DEFAULT_MODEL})")


def parse_control_spec(text: str) -> int:
    """`ctrl|xfrc_applied` or an integer bitmask (`simloader.layout.parse_control_spec`)."""
    try:
        return simloader.layout.parse_control_spec(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def spec_option(parse, option: str):
    """An argparse type from a `cli_specs` parser, whose message names the option once."""
    def read(text: str):
        try:
            return parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e).removeprefix(f"{option}: ")) from None
    read.__name__ = option  # argparse names a failed type by it
    return read


def stream_dataset(args: argparse.Namespace) -> simloader.SimDataset:
    """quickstart's and write's dataset: perturbed initial states, uniform controls unless
    write's `--control` says otherwise, and write's `--randomize` parameters (default none)."""
    record = ({"record": [n.strip() for n in args.record.split(",")]}
              if getattr(args, "record", None) else {})
    randomize = getattr(args, "randomize", None)
    with from_arguments():
        return simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                                    nstep=args.nstep,
                                    control=getattr(args, "control", None)
                                    or simloader.controls.Uniform(),
                                    randomize=randomize or None,
                                    initial_state=simloader.initial.Perturbed(),
                                    terminate=getattr(args, "terminate", None) or None,
                                    record_kinematics=getattr(args, "record_kinematics",
                                                              "before_step"),
                                    num_batches=args.batches, seed=args.seed,
                                    # all cores: nothing here trains alongside the simulation
                                    nthread=threads.available_cpus(), **record)


# quickstart's batch when --nbatch is not given: a GPU is busy only from thousands of
# trajectories on (benchmarks/results/auto_choice-*.md), a CPU from a few per core
GPU_NBATCH, CPU_NBATCH = 8192, 1024


def quickstart_nbatch(args: argparse.Namespace) -> tuple[int, str]:
    """(trajectories per batch, why) for quickstart: as given, else sized for the engines
    that run here."""
    if args.nbatch is not None:
        return args.nbatch, "as given"
    gpu = [name for name in engines_here() if name in backends.on_devices()]
    if args.backend in backends.on_devices() or (args.backend == "auto" and gpu):
        return GPU_NBATCH, "sized for a GPU; --nbatch to change"
    return CPU_NBATCH, "sized for the CPU; --nbatch to change"


def quickstart(args: argparse.Namespace) -> None:
    args.nbatch, sized = quickstart_nbatch(args)
    ds = stream_dataset(args)
    loader = torch.utils.data.DataLoader(ds, batch_size=None)
    print(f"simloader {simloader.__version__}: model {args.model!r}, {args.nbatch} trajectories "
          f"({sized}) x {args.nstep} steps per batch")
    print(f"backend {ds.config.backend!r} ({ds.config.options.simulated_by()}), chosen: "
          f"{ds.config.backend_reason}")
    steps, start, first = 0, time.perf_counter(), None
    for batch in tqdm(loader, total=args.batches, unit="batch",
                      disable=not show_progress(args)):
        if first is None:  # the first batch includes start-up (and compilation for MJX)
            first = time.perf_counter() - start
            start = time.perf_counter()
            shapes = {k: tuple(v.shape) for k, v in batch.items()}
        else:
            steps += batch["state"].shape[0] * batch["state"].shape[1]
        diverged = int(batch["diverged"].sum())
        if diverged:
            tqdm.write(f"{diverged} trajectories diverged in this batch")
    elapsed = time.perf_counter() - start
    print(f"batch tensors: {shapes}")
    print(f"first batch after {first:.2f} s (start-up included)")
    if steps:
        print(f"throughput: {steps / elapsed:,.0f} steps/s ({elapsed * 1e9 / steps:,.0f} ns/step) "
              f"over {args.batches - 1} batches")


def check_out(out: str) -> None:
    """Refuses an --out that cannot be a store, before anything is simulated: an empty path, an
    existing file, or a place this user cannot create it in (the nearest existing folder
    above it not writable).

    Raises:
      BadArgument: naming --out, what was expected and what was given.
    """
    expected = "--out: expected a folder for the store that can be created or resumed"
    if not out.strip():
        raise BadArgument(f"{expected}, got an empty path {out!r}")
    path = os.path.abspath(out)
    if os.path.exists(path) and not os.path.isdir(path):
        raise BadArgument(f"{expected}, got {out!r}, an existing file")
    ancestor = path
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor):
        raise BadArgument(f"{expected}, got {out!r}, below the existing file {ancestor!r}")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        where = "a read-only folder" if ancestor == path else f"the read-only folder {ancestor!r}"
        raise BadArgument(f"{expected}, got {out!r}, {where} (no permission to write there)")


def write(args: argparse.Namespace) -> None:
    check_out(args.out)  # before the dataset: a bad --out fails at once
    ds = stream_dataset(args)
    try:
        # write's argument checks (a system folder, a non-empty folder that is no store, ...)
        # raise ValueError/TypeError: a usage error, without a traceback
        with from_arguments():
            options = {"compression": args.compression} if args.compression else {}
            path = simloader.write(ds, args.out, batches=args.batches, format=args.format,
                                   num_workers=args.num_workers, replace=args.replace,
                                   progress=show_progress(args), **options)
    except StoreLocked as e:  # another job writes it: a message, not a traceback
        raise SystemExit(f"simloader write: {e}") from None
    report = getattr(path, "report", None)
    asked = (f"{args.batches} x {args.nbatch} trajectories of {args.nstep} steps of "
             f"{args.model!r}")
    done = args.batches if report is None else report.batches
    if done == 0:
        said = f"nothing to write: {path} ({args.format}) already holds the {asked}"
    elif done < args.batches:
        said = (f"wrote {done} of the {asked} to {path} ({args.format}); it held the other "
                f"{args.batches - done} batches already")
    else:
        said = f"wrote {asked} to {path} ({args.format})"
    print(f"simloader {simloader.__version__}: {said}")
    if report is not None:  # where the time went, and what bounded the run
        print(f"write: {report}")
    from simloader.store.reader import bytes_on_disk
    kept = bytes_on_disk(str(path))
    steps = args.batches * args.nbatch * args.nstep
    print(f"kept: {kept / 1e6:,.1f} MB on disk for {steps:,} steps, {kept / steps:,.0f} bytes "
          f"per step")
    hint = formats.read_hint(args.format, path)
    if hint:
        print(hint)


def randomized_columns(model: mujoco.MjModel, specs: list[str]) -> dict:
    """{params key: (objects, column names)} of `--randomize FIELD[:OBJ,...]` options, named
    as a SimDataset with those parameters names them (whatever their distribution)."""
    params = []
    for spec in specs:
        field, _, on = spec.partition(":")
        objects = [o.strip() for o in on.split(",") if o.strip()]
        # the distribution does not change the columns: a constant one passes every check
        params.append(simloader.randomize.set(field.strip(), simloader.randomize.Uniform(0, 0),
                                              on=objects or None))
    return simloader.randomize.RandomizationPlan(model, params).columns


def info(args: argparse.Namespace) -> None:
    if args.model and os.path.isfile(os.path.join(args.model, "zarr.json")):
        # a store (one dataset's, or a mixture's of several tasks): what it holds
        with from_arguments():
            stored = simloader.open_store(args.model)
        print(f"the store at {args.model} ({len(stored)} trajectories):")
        print(stored.describe())
        return
    with from_arguments():
        description = simloader.describe(args.model, args.control_spec)
        model = simloader.load_model(args.model)
        if args.record:
            names = [name.strip() for name in args.record.split(",")]
            observations = observe.parse(model, names)
            recorded = simloader.layout.BatchLayout(model, args.control_spec,
                                                    observations).describe()
        if args.randomize:
            randomized = simloader.layout.describe_params(randomized_columns(model,
                                                                             args.randomize))
    print(description)
    print("engines:")
    for line in simloader.backends.acceptance(model):
        print("  " + line)
    # no engine is chosen here: the faults of every engine, each naming its own
    for line in known_faults.described([model], None):
        print(line)
    if args.record:
        print("recorded keys (nbatch, nframes, ...) and their named parts:")
        print(recorded)
    if args.randomize:
        print('randomized: batch["params"] keys and the name of each column '
              '(batch.view(KEY, NAME) finds one):')
        print(randomized)


def bench(args: argparse.Namespace) -> None:
    from simloader import bench as b
    with from_arguments():
        model = simloader.load_model(args.model)
    plot = os.path.join(args.out, args.plot) if args.plot else ""
    if plot:  # before the timing, so that an unusable folder fails at once
        try:
            os.makedirs(os.path.dirname(plot) or ".", exist_ok=True)
        except OSError as e:
            raise BadArgument(f"--out: expected a folder that can be created, got {args.out!r} "
                              f"({e.strerror})") from None
    # every engine that runs here (the GPU engines where a GPU is)
    backends = args.backends or engines_here()
    name = args.model if len(args.model) < 40 else "model"
    w = b.Workload(name, args.nbatch, args.nstep)
    print(f"simloader {simloader.__version__} bench: {w} on {', '.join(backends)}, median of "
          f"{args.repeats} alternating repetitions")
    s_per_step, runs_on, notes = b.compare(
        model, w, backends, repeats=args.repeats, min_seconds=args.min_seconds,
        python_steps=args.python_steps, seed=args.seed)
    print(b.markdown_table(b.HEADERS, b.method_rows(w, s_per_step, runs_on, b.RAW_OF, b.PYTHON)))
    for note in notes:
        print(note)
    if plot:
        b.bar_plot(plot, f"{w}: simloader vs raw", s_per_step)
        print(f"plot saved to {plot}")


BENCH_COMMANDS = ("run", "report", "list")  # `simloader bench run` is the parser "bench-run"


def exit_below_target(lines: list, who: str) -> None:
    """`--check`: exits 1 naming each workload below its target (or failed), if any."""
    from simloader.bench import results
    missed = results.failures(lines)
    if missed:
        print(f"{who}: below target:\n" + "\n".join(f"  {m}" for m in missed),
              file=sys.stderr)
        raise SystemExit(1)


def bench_list(args: argparse.Namespace) -> None:
    """The suite's workloads: name, machine kind, subject, baseline, target and its source."""
    from simloader.bench import workloads
    try:
        chosen = workloads.select(args.workloads, args.suite)
    except ValueError as e:
        raise BadArgument(str(e)) from None
    for b in chosen:
        target = "measured only" if b.target is None else f"target {b.target:.3f}x"
        print(f"{b.name} [{b.suite}] {target}: {b.source}\n    subject:  {b.subject}\n"
              f"    baseline: {b.baseline}")


def bench_run(args: argparse.Namespace) -> None:
    """Runs the suite's workloads, appends their JSON lines to --out, prints the table and,
    with --check, exits 1 naming each workload below its target."""
    import datetime
    import pathlib

    from simloader.bench import results, suite, workloads
    if not args.workloads and args.suite is None:  # the suite of this machine's kind
        import torch
        args.suite = "gpu" if torch.cuda.is_available() else "cpu"
    try:
        chosen = workloads.select(args.workloads, args.suite)
    except ValueError as e:
        raise BadArgument(str(e)) from None
    if not chosen:
        raise BadArgument(f"workloads: none of {args.workloads} is in --suite {args.suite}")
    if args.quick:
        chosen = [workloads.quick(b) for b in chosen]
    if args.repeats is None:
        args.repeats = 5 if args.suite == "cpu" else 3
    out = pathlib.Path(args.out or os.path.join(
        DEFAULT_OUT, f"bench-{args.suite or 'chosen'}-"
                     f"{datetime.date.today().isoformat()}.jsonl"))
    print(f"simloader {simloader.__version__} bench run: {len(chosen)} workloads, "
          f"{args.repeats} alternating repetitions each; lines to {out}")

    def said(line: dict) -> None:
        if line.get("role") != "subject":
            return
        if "error" in line:
            print(f"  {line['workload']}: failed: {line['error']}")
        elif "skipped" in line:
            print(f"  {line['workload']}: skipped: {line['skipped']}")
        else:
            target = "" if line["target"] is None else f" (target {line['target']:.3f})"
            again = line.get("repeated_below_target")
            again = (f", {line['repeats']} repetitions: below its target after the first "
                     f"{line['repeats'] - again}" if again else "")
            print(f"  {line['workload']}: {results.ratio_text(line)}{target}{again}")

    lines = suite.run(chosen, out, repeats=args.repeats, min_seconds=args.min_seconds,
                      seed=args.seed, folder=args.folder, on_line=said)
    print(results.table(lines))
    if args.check:
        exit_below_target(lines, "simloader bench run --check")


def bench_report(args: argparse.Namespace) -> None:
    """Renders JSON lines into NAME.md (a table) and NAME.png (the ratios and targets)."""
    import importlib.util
    import pathlib

    from simloader.bench import results
    if importlib.util.find_spec("matplotlib") is None:  # said before anything is written
        raise SystemExit("simloader bench report: its plot needs matplotlib: pip install "
                         "'simloader[plot]'")
    for path in args.results:
        if not os.path.isfile(path):
            raise BadArgument(f"results: expected a JSON-lines file, got {path!r} (no such file)")
    try:
        lines = results.read_lines(args.results)
    except ValueError as e:
        raise BadArgument(f"results: {e}") from None
    name = args.name or pathlib.Path(args.results[0]).stem
    md, png = results.report(lines, pathlib.Path(args.out), name,
                             args.title or f"simloader bench: {name}", args.note)
    print(f"{md}\n{png}")
    if args.check:
        exit_below_target(lines, "simloader bench report --check")


def check(args: argparse.Namespace) -> None:
    """How far an engine's physics is from MuJoCo C's for the model (`simloader.accuracy`)."""
    from simloader import accuracy
    with from_arguments():
        model = simloader.load_model(args.model) if args.model else DEFAULT_MODEL
        print(accuracy.check(model, args.backend, nbatch=args.nbatch, nstep=args.nstep,
                             seed=args.seed))


def warmup(args: argparse.Namespace) -> None:
    """Simulates one batch of the configuration, which fills the persistent caches (JAX's
    compiled batch function for these sizes; MuJoCo Warp's kernels for this model, which take
    about a minute to compile the first time on a machine), so that later processes start in
    seconds."""
    start = time.perf_counter()
    with from_arguments():
        ds = simloader.SimDataset(args.model, backend=args.backend, nbatch=args.nbatch,
                                  nstep=args.nstep, control=simloader.controls.Uniform(),
                                  num_batches=1)
    print(ds.describe().splitlines()[-1])
    if ds.config.backend not in backends.on_devices():
        print(f"nothing to warm: the {ds.config.backend} engine compiles nothing (MuJoCo's C "
              f"library runs as it is); the GPU engines, {', '.join(backends.on_devices())}, "
              f"are the ones to warm")
        return
    next(iter(ds))
    print(f"warm: compiled in {ds.stats.get('compile_s', 0.0):.1f} s, first batch after "
          f"{time.perf_counter() - start:.1f} s; later processes reuse the caches")


def video(args: argparse.Namespace) -> None:
    """A video of a store's trajectories, or of a batch freshly simulated from a model."""
    rows = args.rows
    if args.out is None:
        raise BadArgument("--out: expected the video file, ending in .mp4 or .gif")
    if os.path.isdir(args.source):  # a store is a folder, a model a name or a file
        # (without --model: the model the store kept, where one model ran every trajectory)
        source, model = args.source, args.video_model
    else:
        with from_arguments():
            source = simloader.SimDataset(
                args.source, nbatch=max(rows) + 1, nstep=args.nstep,
                control=simloader.controls.Uniform(), initial_state=simloader.initial.Perturbed(),
                seed=args.seed)
        model = None
    with from_arguments():
        path = simloader.video(source, args.out, model=model, rows=rows, camera=args.camera,
                               size=tuple(args.size), fps=args.fps, lossless=args.lossless,
                               progress=show_progress(args))
    print(f"simloader: wrote {path}")


def reference() -> str:
    """The command line's reference page (docs/cli.md), made from its parser: every
    subcommand's `--help` (`python -m simloader.cli --reference > docs/cli.md`; a test
    checks the page is current)."""
    parser, sub = build_parser()
    columns = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # the same page whatever the terminal
    try:
        return _reference(parser, sub)
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns


def _reference(parser: argparse.ArgumentParser, sub: Any) -> str:
    parts = ["# Command line", "",
             "Made from the parser (`python -m simloader.cli --reference > docs/cli.md`; a "
             "test checks that it is current).", "", "```text", parser.format_help().rstrip(),
             "```"]
    for name, each in sub.choices.items():
        shown = name.replace("bench-", "bench ")  # `simloader bench run` is "bench-run"
        parts += ["", f"## `simloader {shown}`", "", "```text", each.format_help().rstrip(),
                  "```"]
    return "\n".join(parts) + "\n"


def build_parser() -> tuple[argparse.ArgumentParser, Any]:
    """The command line's parser, and its subcommands' (`main`, `reference`)."""
    parser = ArgumentParser(prog="simloader", description=__doc__)
    parser.add_argument("--version", action="version", version=f"simloader {simloader.__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    add_parser = sub.add_parser

    def add(name: str, **kwargs):  # every subcommand shows its options' defaults
        return add_parser(name, formatter_class=HelpFormatter, **kwargs)
    sub.add_parser = add

    q = sub.add_parser("quickstart", help="stream batches from a model and print throughput")
    add_model_argument(q)
    q.add_argument("--model", dest="model_option", metavar="MODEL",
                   help="the model, as the positional argument (kept for compatibility)")
    q.add_argument("--backend", default="auto", choices=BACKEND_CHOICES, metavar="BACKEND",
                   help="cpu, mjx, warp or auto (default: the fastest here, said at the start)")
    q.add_argument("--nbatch", type=positive_int, default=None,
                   help=f"trajectories per batch (default: {GPU_NBATCH} where a GPU engine "
                        f"runs, else {CPU_NBATCH})")
    q.add_argument("--nstep", type=int, default=200)
    q.add_argument("--batches", type=int, default=20)
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--quiet", action="store_true", help="no progress bar")
    q.set_defaults(run=quickstart)

    wr = sub.add_parser("write", help="simulate batches into a store (zarr or Minari)",
                        description="Simulate batches into a store (zarr or Minari): from "
                                    "perturbed initial states, with uniform controls in the "
                                    "actuators' ranges (--control to choose another "
                                    "generator) and no randomization (--randomize to add "
                                    "some).")
    add_model_argument(wr)
    wr.add_argument("--out", required=True,
                    help="the store: a zarr v3 folder (an existing one of the same settings "
                         "is resumed or grown), or for --format minari the dataset's folder, "
                         "named by its id, e.g. datasets/cartpole-uniform-v0")
    wr.add_argument("--format", default="zarr", choices=tuple(formats.FORMATS))
    wr.add_argument("--backend", default="auto", choices=BACKEND_CHOICES, metavar="BACKEND",
                    help="cpu, mjx, warp or auto (default)")
    wr.add_argument("--nbatch", type=positive_int, default=1024)
    wr.add_argument("--nstep", type=positive_int, default=200)
    wr.add_argument("--batches", type=positive_int, default=20)
    wr.add_argument("--seed", type=int, default=0)
    wr.add_argument("--record", default="",
                    help="names to record, comma-separated (default: state,sensordata)")
    wr.add_argument("--record-kinematics", choices=("before_step", "frame"),
                    default="before_step",
                    help="what derived fields (xpos, sensordata, ...) describe: the state "
                         "before the step, as mj_step leaves them, or the frame itself, as "
                         "mj_forward computes them (a forward pass per frame)")
    wr.add_argument("--control", type=spec_option(cli_specs.parse_control, "--control"),
                    default=None, metavar="SPEC",
                    help="the control generator of simloader.controls, by name with keyword "
                         "arguments, e.g. 'normal(std=0.5)', 'ou(std=0.3, tau=0.05)', "
                         "'piecewiseconstant(hold=20)', 'sinusoid(frequency=(0.5, 2))'; "
                         f"names: {', '.join(cli_specs.CONTROLS)} (ou: OrnsteinUhlenbeck) "
                         "(default: uniform, each actuator uniform in its ctrlrange, [-1, 1] "
                         "where unlimited, drawn fresh every step)")
    wr.add_argument("--randomize", type=spec_option(cli_specs.parse_randomize, "--randomize"),
                    action="append", default=[], metavar=cli_specs.RANDOMIZE_FORM,
                    help="a randomized model parameter of simloader.randomize, repeatable, "
                         "e.g. 'body_mass:pole=scale:uniform(0.8, 1.2)' or "
                         "'dof_damping:hinge=add:normal(0, 0.01, low=0)'; OP: set, scale or "
                         "add; DIST: uniform(low, high), loguniform(low, high), "
                         "normal(mean, std, low=, high=) (default: no randomization)")
    wr.add_argument("--num-workers", type=int, default=0,
                    help="DataLoader workers that simulate and write in parallel")
    wr.add_argument("--compression", choices=("zstd",), default=None,
                    help="compress the states too (zarr's blosc codec: byte shuffle, zstd): "
                         "pays where the disk bounds the write (default: states raw, images "
                         "zstd)")
    wr.add_argument("--replace", action="store_true",
                    help="replace a store (or Minari dataset) of other settings at --out "
                         "instead of refusing it")
    wr.add_argument("--terminate", type=spec_option(cli_specs.parse_terminate, "--terminate"),
                    action="append", default=[], metavar="RULE(ARGS)",
                    help="episodes that end, repeatable (any rule ends one): a rule of "
                         "simloader.terminate, e.g. 'below(torso, 0.8)', 'tilted(torso, 1.0)', "
                         "'outside(hinge, -0.2, 0.2)', 'timelimit(500)'; the store then keeps "
                         "terminated/truncated/first (default: none, every trajectory runs "
                         "its nstep steps)")
    wr.add_argument("--quiet", action="store_true",
                    help="no progress bar (none either where stderr is not a terminal)")
    wr.set_defaults(run=write)

    i = sub.add_parser("info", help="print which state/control/sensor columns mean what")
    i.add_argument("model", nargs="?", default=None,
                   help=f"built-in model name or MJCF/MJB path (default: the built-in "
                        f"{DEFAULT_MODEL}), or a store's folder (what it holds; a mixture's "
                        f"store: which columns of each task mean what)")
    i.add_argument("--control-spec", type=parse_control_spec,
                   default=int(mujoco.mjtState.mjSTATE_CTRL),
                   help="components of the control vector, e.g. 'ctrl|xfrc_applied' (default ctrl)")
    i.add_argument("--record", default="",
                   help="names to record, e.g. 'qpos,xpos,sensor:tip_pos': what each key holds")
    i.add_argument("--randomize", action="append", default=[], metavar="FIELD[:OBJ,...]",
                   help="a randomized parameter, e.g. 'body_mass:pole' or 'geom_friction': "
                        "its batch[\"params\"] key and what each column is (repeatable)")
    i.set_defaults(run=info)

    b = sub.add_parser("bench", help="time simloader's backends next to the raw simulators "
                                     "(and `simloader bench run|report|list`: the suite)",
                       description="One model on every engine here, next to the raw "
                                   "simulators and a Python loop. The suite of named "
                                   "workloads with targets is `simloader bench run`, "
                                   "`simloader bench report` and `simloader bench list`.")
    add_model_argument(b)
    b.add_argument("--backends", nargs="+", choices=("cpu", "mjx", "warp"),
                   help="default: cpu, and the GPU engines that run here")
    b.add_argument("--nbatch", type=positive_int, default=1024)
    b.add_argument("--nstep", type=positive_int, default=200)
    b.add_argument("--repeats", type=positive_int, default=3,
                   help="alternating timed repetitions")
    b.add_argument("--min-seconds", type=float, default=2.0,
                   help="each timed repetition lasts at least this long")
    b.add_argument("--python-steps", type=positive_int, default=5000,
                   help="steps of the single-environment Python loop per repetition")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", default=DEFAULT_OUT,
                   help=f"folder for the bar chart, created when needed (default: {DEFAULT_OUT}/)")
    b.add_argument("--plot", default="simloader-bench.png",
                   help="file name of the bar chart in --out ('' for none)")
    b.set_defaults(run=bench)

    def workload_arguments(p: argparse.ArgumentParser) -> None:
        p.add_argument("workloads", nargs="*", metavar="WORKLOAD",
                       help="names from `simloader bench list` (default: every workload of "
                            "--suite; `bench run` with neither: the suite of this machine, "
                            "gpu where torch sees a CUDA GPU, else cpu)")
        p.add_argument("--suite", choices=("cpu", "gpu", "several-gpus"),
                       help="the machine kind: cpu (any machine, the CPU engine), gpu (an "
                            "NVIDIA GPU: MJX and MuJoCo Warp) or several-gpus (2 or 4 GPUs of "
                            "one host: torchrun ranks and sim_device; a workload needing more "
                            "GPUs than the machine has is skipped, saying so)")
        p.set_defaults(model=None)

    br = sub.add_parser("bench-run", prog="simloader bench run",
                        help="= `simloader bench run`: the suite's workloads, held to targets")
    workload_arguments(br)
    br.add_argument("--check", action="store_true",
                    help="exit 1 if a workload is below its target, naming it")
    br.add_argument("--quick", action="store_true",
                    help="smoke-test sizes (a 64th of the trajectories, a tenth of the steps): "
                         "that every part runs here, not the targets")
    br.add_argument("--out", help="the JSON-lines file the results are appended to (default: "
                                  f"{DEFAULT_OUT}/bench-SUITE-DATE.jsonl)")
    br.add_argument("--repeats", type=positive_int, default=None,
                    help="alternating timed repetitions per workload (default: 5 on --suite "
                         "cpu, where a shared 2-core machine drifts, else 3); a workload below "
                         "its target runs as many again, pooled, before its verdict")
    br.add_argument("--min-seconds", type=float, default=1.5,
                    help="each timed repetition lasts at least this long")
    br.add_argument("--seed", type=int, default=0)
    br.add_argument("--folder", help="where stores and start-up caches go while measured: a "
                                     "temporary folder made in it (default: the system's), "
                                     "removed at the end")
    br.set_defaults(run=bench_run)

    bp = sub.add_parser("bench-report", prog="simloader bench report",
                        help="= `simloader bench report`: tables and plots from results")
    bp.add_argument("results", nargs="+", help="JSON-lines files of `simloader bench run`")
    bp.add_argument("--out", default=DEFAULT_OUT, help="folder for NAME.md and NAME.png")
    bp.add_argument("--name", help="file name without suffix (default: the first file's)")
    bp.add_argument("--title", help="the table's and plot's title")
    bp.add_argument("--note", action="append", default=[],
                    help="a paragraph under the title (repeatable): the command, what differs")
    bp.add_argument("--check", action="store_true",
                    help="exit 1 if the latest row of a workload is below its target")
    bp.set_defaults(run=bench_report, model=None)

    bl = sub.add_parser("bench-list", prog="simloader bench list",
                        help="= `simloader bench list`: the suite's workloads and targets")
    workload_arguments(bl)
    bl.set_defaults(run=bench_list)

    w = sub.add_parser("warmup", help="compile a GPU engine for a model ahead of time")
    add_model_argument(w)
    w.add_argument("--backend", default="auto", choices=("auto", *backends.on_devices()),
                   help="the GPU engine to compile (default: the one auto picks)")
    w.add_argument("--nbatch", type=int, default=1024,
                   help="trajectories per batch, as the training run will use them")
    w.add_argument("--nstep", type=int, default=200, help="steps per batch, as in training")
    w.set_defaults(run=warmup)

    c = sub.add_parser("check", help="how far an engine's physics is from MuJoCo C's for a "
                                     "model (largest differences in positions, velocities)")
    add_model_argument(c)
    c.add_argument("--backend", default="auto", choices=BACKEND_CHOICES, metavar="BACKEND",
                   help="the engine to check: cpu, mjx, warp or auto (default)")
    c.add_argument("--nbatch", type=positive_int, default=16, help="trajectories")
    c.add_argument("--nstep", type=positive_int, default=50, help="steps per trajectory")
    c.add_argument("--seed", type=int, default=0, help="of the random controls")
    c.set_defaults(run=check)

    v = sub.add_parser("video", help="write an MP4 or GIF of trajectories of a store or a model",
                       description="Write an MP4 (or GIF) of trajectories side by side: of a "
                                   "store (rendered from its states with the model it kept, or "
                                   "--model, or from its recorded camera), or of a batch "
                                   "simulated from a model on the CPU (uniform controls, "
                                   "perturbed initial states).")
    v.add_argument("source", help="a store folder, or a built-in model name or MJCF path")
    v.add_argument("out_file", nargs="?", default=None, metavar="OUT",
                   help="the video file, ending in .mp4 or .gif (or --out)")
    v.add_argument("--out", default=None,
                   help="the video file, ending in .mp4 or .gif, as write's --out")
    v.add_argument("--model", dest="video_model", default=None, metavar="MODEL",
                   help="for a store: the model to render its states with (default: the one "
                        "it kept; needed for a store of a model list, variants or "
                        "randomized values)")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.add_argument("--rows", type=int, nargs="+", default=[0, 1, 2, 3],
                   help="the trajectories to show (default: 0 1 2 3)")
    v.add_argument("--camera", default=None,
                   help="a recorded camera's name, or a model camera to render (default: the "
                        "recorded one, else the free camera)")
    v.add_argument("--size", type=positive_int, nargs=2, default=[240, 320],
                   metavar=("HEIGHT", "WIDTH"), help="pixels of one trajectory (default 240 320)")
    v.add_argument("--fps", type=float, default=None,
                   help="frames per second (default: real time, at most 60)")
    v.add_argument("--lossless", action="store_true", help="MP4 only: exact RGB frames")
    v.add_argument("--nstep", type=positive_int, default=500,
                   help="for a model: steps to simulate (default 500)")
    v.add_argument("--seed", type=int, default=0, help="for a model: the seed (default 0)")
    v.set_defaults(run=video, model=None)

    for each in sub.choices.values():  # every option says what it is (and its default)
        for action in each._actions:
            if action.help is None and action.option_strings:
                action.help = OPTION_HELP.get(action.option_strings[0], action.dest)
    return parser, sub


def main(argv: list[str] | None = None) -> None:
    parser, sub = build_parser()
    if argv is None and sys.argv[1:] == ["--reference"]:  # docs/cli.md
        print(reference(), end="")
        return
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["bench"] and argv[1:2] and argv[1] in BENCH_COMMANDS:
        argv = [f"bench-{argv[1]}", *argv[2:]]  # `simloader bench run` is "bench-run"
    args = parser.parse_args(argv)
    sub_parser = sub.choices[args.command]
    option = getattr(args, "model_option", None)
    if option is not None and args.model is not None and option != args.model:
        sub_parser.error(f"model: given twice and differently, {args.model!r} (positional) and "
                         f"--model {option!r}; give one")
    if not args.command.startswith("bench-"):
        args.model = args.model or option or DEFAULT_MODEL
    if args.command == "video":  # the file: positional or --out, as write's --out
        if args.out_file is not None and args.out is not None and args.out_file != args.out:
            sub_parser.error(f"out: given twice and differently, {args.out_file!r} "
                             f"(positional) and --out {args.out!r}; give one")
        args.out = args.out or args.out_file
    try:
        args.run(args)
    except BadArgument as e:
        sub_parser.error(str(e))
    except KeyboardInterrupt:  # Ctrl-C: one line, the shell's status for an interrupt
        kept = (f"; the store at {args.out} keeps every batch committed before it (the same "
                f"command resumes)" if args.command == "write" else "")
        print(f"simloader {args.command}: interrupted{kept}", file=sys.stderr)
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
