"""The engine contract: every built-in engine's entry offers the `Engine` protocol, and an
engine written outside simloader joins with `register_engine` and streams batches (recorded
state and sensors, control generators, randomized parameters) without any shared module
edited. The outside engine here is small on purpose: `mujoco.rollout` on one thread, one
model copy per trajectory for the randomized values; since the CPU engine is bit for bit
`mujoco.rollout` on the same inputs, its batches must equal the CPU engine's exactly."""

import copy
import dataclasses
import pathlib
import subprocess
import sys

import mujoco
import numpy as np
import pytest
import torch
from mujoco import rollout

import simloader
from simloader import backends, seeds
from simloader import randomize as dr
from simloader.backends import base, contract
from simloader.backends.contract import EngineEntry, Job


REPO = pathlib.Path(__file__).resolve().parent.parent
# the type checker reads simloader's own modules only: the engines' libraries are skipped
MYPY_INI = """
[mypy]
follow_imports = silent
ignore_missing_imports = True
[mypy-torch.*,jax.*,jaxlib.*,mujoco.*,warp.*,mujoco_warp.*,numpy.*,zarr.*]
follow_imports = skip
"""


def _mypy(tmp_path, *files):
    ini = tmp_path / "mypy.ini"
    ini.write_text(MYPY_INI)
    return subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(ini),
                           "--cache-dir", str(tmp_path / "cache"), *map(str, files)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)


def test_entries_meet_the_protocol_statically_and_a_wrong_one_does_not(tmp_path):
    # each entry.py annotates `ENGINE: Engine`, so a type checker holds the entry's methods
    # to the protocol's signatures, as mjlab checks its backends
    pytest.importorskip("mypy")
    entries = [REPO / "simloader" / "backends" / e / "entry.py" for e in ("cpu", "mjx", "warp")]
    done = _mypy(tmp_path, *entries)
    assert done.returncode == 0, done.stdout + done.stderr
    wrong = tmp_path / "wrong_entry.py"
    wrong.write_text(
        "from simloader.backends.contract import Engine, EngineEntry\n\n\n"
        "class Wrong(EngineEntry):\n"
        "    name = 'wrong'\n\n"
        "    def create(self, config):  # the shard and stats forgotten\n"
        "        return None\n\n\n"
        "ENGINE: Engine = Wrong()\n")
    done = _mypy(tmp_path, wrong)
    assert done.returncode == 1 and "create" in done.stdout, done.stdout + done.stderr


@pytest.mark.parametrize("name", ["cpu", "mjx", "warp"])
def test_every_built_in_entry_offers_the_engine_protocol(name):
    engine = backends.engine(name)
    assert isinstance(engine, contract.Engine) and engine.name == name
    job = Job(step_s=2e-6, nbatch=1024, contacts=False, cores=2, policy=False, cameras=False)
    assert engine.estimate(job) > 0


def test_entries_import_no_engine_runtime(fresh_python):
    script = """
import sys
from simloader import backends
for name in ("cpu", "mjx", "warp"):
    backends.engine(name).missing()
print(sorted(m for m in ("jax", "warp", "mujoco_warp") if m in sys.modules))
"""
    out, = fresh_python(script, [([], {})])
    assert out.strip().splitlines()[-1] == "[]"


@dataclasses.dataclass(frozen=True)
class SerialOptions:
    threads: int

    def simulated_by(self) -> str:
        return f"mujoco.rollout on {self.threads} thread (a test engine)"


class SerialBackend(base.Backend):
    """Each batch: initial states and controls drawn as every engine draws them, randomized
    values applied to one model copy per trajectory, then one `mujoco.rollout` call."""

    def produce(self, index):
        c = self.config
        x0 = c.initial.sample(self.seed(index, seeds.INITIAL), c.nbatch)
        control = np.empty((c.nbatch, c.nstep, c.ncontrol))
        c.control.sample_numpy(self.seed(index, seeds.CONTROL), control)
        params = self.draw_models(index)
        models = []
        for i in range(c.nbatch):
            m = copy.copy(c.model)
            for r in (c.randomization.resolved if c.randomization else ()):
                getattr(m, r.field).reshape(-1)[r.elements] = params[r.param.key][i]
            models.append(m)
        state, sensordata = rollout.rollout(models, mujoco.MjData(c.model), x0, control)
        return x0, control, params, state, sensordata

    def deliver(self, produced):
        x0, control, params, state, sensordata = produced
        self.stats.add(batches=1, steps=self.config.nbatch * self.config.nstep, rollouts=1)
        out = {"state": torch.from_numpy(state), "sensordata": torch.from_numpy(sensordata),
               "control": torch.from_numpy(control), "initial_state": torch.from_numpy(x0),
               "diverged": torch.from_numpy(~np.isfinite(state).all(axis=(1, 2)))}
        if params:
            out["params"] = {k: torch.from_numpy(v) for k, v in params.items()}
        return out


class SerialEngine(EngineEntry):
    name = "serial_test"
    options = ("threads",)
    counters = ("rollouts",)  # its own, in ds.stats

    def check_options(self, config, options, reason):
        if [o.key for o in config.observations] != ["state", "sensordata"]:
            raise ValueError("record: the serial engine records state and sensordata only")
        return SerialOptions(options.get("threads", 1))

    def create(self, config, shard, stats):
        return SerialBackend(config, shard, stats)


@pytest.fixture
def serial():
    backends.register_engine(SerialEngine())
    yield
    backends.unregister_engine("serial_test")


def test_an_engine_from_outside_streams_what_the_cpu_engine_streams(serial):
    kwargs = dict(nbatch=6, nstep=25, num_batches=2, seed=3,
                  control=simloader.controls.Uniform(),
                  initial_state=simloader.initial.Perturbed(),
                  randomize=[dr.scale("dof_damping", dr.Uniform(0.5, 2.0))])
    ds = simloader.SimDataset("cartpole", backend="serial_test", threads=1, **kwargs)
    assert ds.stats["backend"] == "serial_test"
    assert "simulated by: backend='serial_test' (mujoco.rollout on 1 thread (a test engine); " \
           "chosen: asked)" in ds.describe()
    cpu = simloader.SimDataset("cartpole", backend="cpu", nthread=1, **kwargs)
    theirs = list(torch.utils.data.DataLoader(ds, batch_size=None))
    ours = list(cpu)
    assert len(theirs) == len(ours) == 2
    # each engine's counters are its own: none of MJX's or Warp's on the CPU engine
    assert ds.stats["batches"] == ds.stats["rollouts"] == 2
    assert "rollouts" not in cpu.stats
    assert not {"compile_s", "overflow", "graph_captures"} & set(cpu.stats)
    assert cpu.stats["batches"] == 2
    for a, b in zip(theirs, ours):
        for key in ("state", "sensordata", "control", "initial_state", "diverged"):
            assert torch.equal(a[key], b[key]), key
        assert a["params"].keys() == b["params"].keys()
        for key in a["params"]:
            assert torch.equal(a["params"][key], b["params"][key])
    # its options are its own; the CPU engine's are refused by name
    with pytest.raises(TypeError, match=r"\['threads'\] for backend='cpu'.*'threads' is an "
                                        r"option of backend='serial_test'"):
        simloader.SimDataset("cartpole", backend="cpu", threads=1, nbatch=2, nstep=2)
    # auto never takes an engine that estimates nothing
    assert simloader.SimDataset("cartpole", nbatch=2, nstep=2).config.backend != "serial_test"


def test_register_engine_refuses_what_is_not_an_engine():
    with pytest.raises(TypeError, match="Engine protocol"):
        backends.register_engine(object())
    taken = SerialEngine()
    taken.name = "cpu"
    with pytest.raises(ValueError, match="name 'cpu' is taken"):
        backends.register_engine(taken)
