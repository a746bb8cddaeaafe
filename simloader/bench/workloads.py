"""The suite's workloads as data: each a named comparison held to a target.

A workload compares a *subject* (what simloader delivers) with a *baseline* (the raw engine doing
the same work, or the same stream without the feature whose cost is measured) and holds the
throughput ratio subject / baseline to a target from `shared/design/performance.md` (its number
in `source`). Streams are written in `simloader write`'s words (`cli_specs`), so a row reads as
the command a user would type and can be printed, stored and compared as plain data.

`simloader bench run` runs them (`suite.py`); `simloader bench list` prints them.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

SUITES = ("cpu", "gpu", "several-gpus")

# what each side of a comparison is (`suite.METHODS` builds them)
SIMLOADER = "simloader"          # the stream, delivered (tensors in hand)
RAW = "raw"                      # the raw engine, same work, worlds restarted every batch
RAW_CONTINUED = "raw continued"  # the same, worlds continued from batch to batch
WRITE = "write"                  # simloader.write of the stream into a store
WRITE_BOUND = "generation or disk"  # the lower of generating the stream and the disk's bound
READ_RENDER = "render on read"   # a store of the stream's states rendering its camera on read
MIXTURE = "mixture"              # Mixture of the streams, equal weights
MEMBERS = "members alone"        # the same batches, each member streamed alone
STARTUP = "first batch"          # a fresh process to its first batch (caches warm)
RAW_STARTUP = "raw first batch"  # a raw script of the engine, the same
RANKS = "ranks"                  # `count` processes under torchrun, one per GPU (per GPU)
SIM_DEVICES = "simulation GPUs"  # delivered on cuda:0, simulated on `count` others (per GPU)


@dataclasses.dataclass(frozen=True)
class Stream:
    """A `SimDataset` as data, in `simloader write`'s words.

    Controls are `Uniform()` draws within each actuator's range; `record` is the dataset's
    default unless given; `camera` is camera 0 at (height, width), recorded beside the state,
    with MuJoCo's shadow maps and multisampling unless `camera_quality` is False (what a
    software renderer wants: `Camera(shadows=False, multisample=False)`); `policy` is the
    benchmark policy (a 2 x 256 tanh MLP of qpos and qvel); `terminate` and `randomize` are
    `--terminate` and `--randomize` specs. On the CPU engine the stream simulates on all the
    cores (as the raw rollout), or with its default threads (`all_cores=False`: a core left to
    the consumer, as when writing a store).
    """

    model: str
    engine: str
    nbatch: int
    nstep: int
    record: tuple[str, ...] = ()
    terminate: tuple[str, ...] = ()
    continue_episodes: bool = False
    randomize: tuple[str, ...] = ()
    policy: bool = False
    camera: Optional[tuple[int, int]] = None
    camera_quality: bool = True
    all_cores: bool = True

    @property
    def steps(self) -> int:
        return self.nbatch * self.nstep

    def __str__(self) -> str:
        parts = [f"{self.engine} {self.model} {self.nbatch}x{self.nstep}"]
        parts += [f"record={','.join(self.record)}"] if self.record else []
        parts += [f"camera {self.camera[0]}x{self.camera[1]}"
                  + ("" if self.camera_quality else " (no shadows, no multisampling)")] \
            if self.camera else []
        parts += [f"terminate={' + '.join(self.terminate)}"] if self.terminate else []
        parts += ["continued"] if self.continue_episodes else []
        parts += [f"randomize={' + '.join(self.randomize)}"] if self.randomize else []
        parts += ["policy 2x256"] if self.policy else []
        parts += ["default threads"] if self.engine == "cpu" and not self.all_cores else []
        return ", ".join(parts)

    def but(self, **changes) -> "Stream":
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True)
class Method:
    """One side of a comparison: what is done (`kind`) with which streams."""

    kind: str
    streams: tuple[Stream, ...]
    count: int = 1  # RANKS: processes; SIM_DEVICES: simulation GPUs

    @property
    def gpus(self) -> int:
        """The GPUs its machine must have for it to run at all: a GPU a rank; the simulation
        GPUs and the one delivering (0: a stream of the CPU engine, or one GPU process,
        which fails where it cannot run rather than being skipped)."""
        if all(s.engine == "cpu" for s in self.streams):
            return 0
        return {RANKS: self.count, SIM_DEVICES: self.count + 1}.get(self.kind, 0)

    def __str__(self) -> str:
        kind = self.kind
        if kind in (RANKS, SIM_DEVICES):  # "2 ranks", "1 rank"
            kind = f"{self.count} {kind if self.count > 1 else kind.removesuffix('s')}"
        return f"{kind}: " + " & ".join(map(str, self.streams))


@dataclasses.dataclass(frozen=True)
class Benchmark:
    """A named workload: subject / baseline throughput held to `target` on `suite`'s machine.

    `target` None: measured and reported, not checked (a fact the suite tracks, such as a
    physics cost). `ceiling_s`: also, the subject's time to its first batch after importing
    torch is at most this (start-up on the CPU). `source`: where the target is set.
    `min_calls`: batches per timed repetition at least (more where a repetition has a fixed
    cost to amortize: a store's creation, a mixture's draws). `gpus`: the GPUs its machine
    needs (a run on fewer skips it, saying so).
    """

    name: str
    suite: str
    subject: Method
    baseline: Method
    target: Optional[float]
    source: str
    unit: str = "steps"
    ceiling_s: Optional[float] = None
    min_calls: int = 2

    @property
    def gpus(self) -> int:
        return max(self.subject.gpus, self.baseline.gpus)


def _m(kind: str, *streams: Stream) -> Method:
    return Method(kind, streams)


def _pair(name: str, suite: str, subject: Stream, baseline: Stream, target: Optional[float],
          source: str, kind: str = SIMLOADER) -> Benchmark:
    """The stream against itself without a feature (both delivered by simloader)."""
    return Benchmark(name, suite, _m(kind, subject), _m(SIMLOADER, baseline), target, source)


def _cpu() -> list[Benchmark]:
    cart = Stream("cartpole", "cpu", 1024, 200)
    human = Stream("humanoid", "cpu", 128, 100)
    # a software renderer draws MuJoCo's 4096-pixel shadow maps slowly: off, on both sides
    cam = Stream("cartpole", "cpu", 64, 20, record=("state",), camera=(64, 64),
                 camera_quality=False)
    fall = "outside(hinge, -0.2, 0.2)"
    return [
        Benchmark("cpu-open-loop-cartpole", "cpu", _m(SIMLOADER, cart), _m(RAW, cart), 0.95,
                  "target 1 (CPU: 0.95x raw mujoco.rollout on all cores)"),
        Benchmark("cpu-open-loop-humanoid", "cpu", _m(SIMLOADER, human), _m(RAW, human), 0.95,
                  "target 1"),
        # target 14 names the GPU engines. The CPU engine checks the rules between frames of
        # MuJoCo's batch, a Python step per frame where the stream without rules is one
        # mujoco.rollout call: measured (0.58-0.76 on 2 cores, a light cart-pole the worst)
        _pair("cpu-episodes", "cpu", cart.but(terminate=(fall, "timelimit(150)")), cart, None,
              "measured only (target 14 is the GPU engines')"),
        _pair("cpu-episodes-humanoid", "cpu",
              human.but(terminate=("below(torso, 0.9)", "timelimit(150)"),
                        continue_episodes=True),
              human.but(continue_episodes=True), None,
              "measured only (target 14 is the GPU engines')"),
        _pair("cpu-randomize", "cpu", cart.but(randomize=("body_mass=scale:uniform(0.8, 1.2)",)),
              cart, None, "measured only (one model per trajectory is MuJoCo's own cost)"),
        _pair("cpu-record", "cpu", human.but(record=("qpos", "qvel", "xpos")),
              human.but(record=("state",)), None, "measured only (target 13 is for GPUs)"),
        Benchmark("cpu-camera", "cpu", _m(SIMLOADER, cam), _m(RAW, cam), 0.9,
                  "target 8 (0.9x raw mujoco.Renderer threads)", unit="frames"),
        # the writer's own work needs a core: the default threads, on both sides
        Benchmark("cpu-write", "cpu", _m(WRITE, cart.but(all_cores=False)),
                  _m(SIMLOADER, cart.but(all_cores=False)), 0.85,
                  "target 13 (the CPU engine's write cost at most 15%)", min_calls=8),
        Benchmark("cpu-render-on-read", "cpu", _m(READ_RENDER, cam), _m(SIMLOADER, cam), 0.8,
                  "target 15 (0.8x streaming the camera)", unit="frames"),
        Benchmark("cpu-mixture", "cpu", _m(MIXTURE, cart.but(nbatch=256), human),
                  _m(MEMBERS, cart.but(nbatch=256), human), 0.9,
                  "target 16 (0.9x the members alone, time-weighted)", min_calls=10),
        # three fresh processes per repetition: importing torch varies by a tenth of a second
        Benchmark("cpu-startup", "cpu", _m(STARTUP, cart.but(nbatch=64, nstep=20)),
                  _m(RAW_STARTUP, cart.but(nbatch=64, nstep=20)), 1 / 1.05,
                  "target 4 (first batch at most 1.05x a raw script; 0.5 s after torch)",
                  unit="first batches", ceiling_s=0.5, min_calls=3),
    ]


def _gpu() -> list[Benchmark]:
    human = Stream("humanoid", "warp", 8192, 200)
    small = Stream("humanoid", "warp", 4096, 100)
    cart = Stream("cartpole", "mjx", 8192, 1000)
    cam = Stream("cartpole", "warp", 16384, 50, record=("state",), camera=(64, 64))
    below, limit = "below(torso, 0.9)", "timelimit(150)"
    out = [
        Benchmark("warp-open-loop", "gpu", _m(SIMLOADER, human), _m(RAW, human), 0.97,
                  "targets 1 and 6 (0.97x a raw MuJoCo Warp graph loop, same work)"),
        Benchmark("mjx-open-loop", "gpu", _m(SIMLOADER, cart), _m(RAW, cart), 0.97,
                  "target 1 (0.97x a raw jitted vmap+scan)"),
        Benchmark("warp-continued", "gpu", _m(SIMLOADER, small.but(continue_episodes=True)),
                  _m(RAW_CONTINUED, small), 0.97,
                  "targets 1 and 6, against a raw loop whose worlds continue too"),
        Benchmark("warp-continued-physics", "gpu", _m(RAW_CONTINUED, small), _m(RAW, small),
                  None, "measured only: raw MuJoCo Warp, continued worlds against restarted "
                  "ones (a fallen humanoid's contacts; issue 65's 0.97x is not simloader's)"),
        # the policy observes what is recorded: qpos and qvel, recorded by the open loop too
        _pair("warp-policy", "gpu", human.but(policy=True, record=("state", "qpos", "qvel")),
              human.but(record=("state", "qpos", "qvel")), 0.95,
              "target 7 (a torch policy in the loop at 0.95x open loop)"),
        _pair("mjx-episodes", "gpu", cart.but(terminate=("outside(hinge, -0.2, 0.2)",)), cart,
              0.95, "target 14"),
        Benchmark("warp-camera", "gpu", _m(SIMLOADER, cam), _m(RAW, cam), 0.95,
                  "target 8 (0.95x the raw step+render loop)", unit="frames"),
        _pair("warp-randomize", "gpu",
              human.but(randomize=("body_mass=scale:uniform(0.8, 1.2)",)), human, 0.95,
              "the randomization benchmark's target (randomized / plain >= 0.95)"),
        _pair("warp-record", "gpu", human.but(record=("qpos", "qvel", "xpos")),
              human.but(record=("state",)), 0.95, "recording named fields costs at most 5%"),
        Benchmark("warp-write", "gpu", _m(WRITE, human), _m(WRITE_BOUND, human), 0.8,
                  "target 13 (0.8x the lower of generation and the disk's bound)", min_calls=8),
        Benchmark("warp-render-on-read", "gpu", _m(READ_RENDER, cam.but(nbatch=1024)),
                  _m(SIMLOADER, cam.but(nbatch=1024)), 0.8, "target 15", unit="frames"),
        Benchmark("warp-mixture", "gpu", _m(MIXTURE, human, small),
                  _m(MEMBERS, human, small), 0.9, "target 16", min_calls=10),
        # two fresh processes per repetition: importing torch varies by half a second here
        Benchmark("warp-startup", "gpu", _m(STARTUP, human), _m(RAW_STARTUP, human), 1 / 1.05,
                  "target 4 (warm caches)", unit="first batches", min_calls=2),
        Benchmark("mjx-startup", "gpu", _m(STARTUP, cart.but(nbatch=4096, nstep=200)),
                  _m(RAW_STARTUP, cart.but(nbatch=4096, nstep=200)), 1 / 1.05,
                  "target 4 (warm caches)", unit="first batches", min_calls=1),
    ]
    # episodes: with and without TimeLimit, with and without continuation, at both sizes,
    # each against the same stream without rules (continued alike)
    for size in (small, human):
        for rules in ((below,), (below, limit)):
            for continued in (False, True):
                name = (f"warp-episodes-{size.nbatch}x{size.nstep}-"
                        f"{'below' if len(rules) == 1 else 'below-timelimit'}"
                        f"{'-continued' if continued else ''}")
                base = size.but(continue_episodes=continued)
                out.append(_pair(name, "gpu", base.but(terminate=rules), base, 0.95,
                                 "target 14 and issue 65 (episodes at 0.95x)"))
    return out


def _several_gpus() -> list[Benchmark]:
    """Target 5: one process per GPU under torchrun (per GPU against one GPU alone), and
    simulation on other GPUs than the one delivering (`sim_device`), per simulation GPU."""
    human = Stream("humanoid", "warp", 8192, 200)
    cart = Stream("cartpole", "mjx", 8192, 1000)
    # the sim_device benchmark's per-GPU workload (benchmarks/sim_devices.py)
    split = Stream("humanoid", "warp", 8192, 100)
    ranks = "target 5 ({}x one GPU on {} GPUs, one process each under torchrun)"
    return [
        Benchmark("warp-2-ranks", "several-gpus", Method(RANKS, (human,), 2),
                  Method(RANKS, (human,), 1), 1.95 / 2, ranks.format(1.95, 2)),
        Benchmark("mjx-2-ranks", "several-gpus", Method(RANKS, (cart,), 2),
                  Method(RANKS, (cart,), 1), 1.95 / 2, ranks.format(1.95, 2)),
        Benchmark("warp-4-ranks", "several-gpus", Method(RANKS, (human,), 4),
                  Method(RANKS, (human,), 1), 3.9 / 4, ranks.format(3.9, 4)),
        Benchmark("warp-sim-device", "several-gpus", Method(SIM_DEVICES, (split,), 1),
                  _m(SIMLOADER, split), None,
                  "measured only: simulated on cuda:1 and delivered on cuda:0, against the "
                  "same stream simulated where it is delivered"),
        Benchmark("warp-3-sim-devices", "several-gpus", Method(SIM_DEVICES, (split,), 3),
                  Method(SIM_DEVICES, (split,), 1), 2.85 / 3,
                  "target 5 (three simulation GPUs feed one trainer at 2.85x one's)"),
    ]


ALL: tuple[Benchmark, ...] = tuple(_cpu() + _gpu() + _several_gpus())
BY_NAME = {b.name: b for b in ALL}
assert len(BY_NAME) == len(ALL), "workload names repeat"


def quick(b: Benchmark) -> Benchmark:
    """`b` at smoke-test sizes (a 64th of the trajectories, a tenth of the steps): checks that
    every part of the suite runs here, not the targets."""
    def small(m: Method) -> Method:
        return Method(m.kind, tuple(s.but(nbatch=max(8, s.nbatch // 64),
                                          nstep=max(5, s.nstep // 10)) for s in m.streams),
                      m.count)
    return dataclasses.replace(b, subject=small(b.subject), baseline=small(b.baseline))


def select(names: list[str], suite: Optional[str]) -> list[Benchmark]:
    """The workloads named (all of `suite` when none is), in the table's order.

    Raises:
      ValueError: a name is not in the table, or `suite` is not one of `SUITES`.
    """
    if suite is not None and suite not in SUITES:
        raise ValueError(f"suite: expected one of {', '.join(SUITES)}, got {suite!r}")
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise ValueError(f"workloads: no workload named {', '.join(map(repr, unknown))} "
                         f"(`simloader bench list` prints them)")
    chosen = [BY_NAME[n] for n in names] if names else list(ALL)
    return [b for b in chosen if suite is None or b.suite == suite]
