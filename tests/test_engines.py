"""The engine contract: every built-in engine's entry offers the `Engine` protocol, and an
engine written outside simloader joins with `register_engine` and streams batches (recorded
state and sensors, control generators, randomized parameters) without any shared module
edited. The outside engine here is small on purpose: `mujoco.rollout` on one thread, one
model copy per trajectory for the randomized values; since the CPU engine is bit for bit
`mujoco.rollout` on the same inputs, its batches must equal the CPU engine's exactly."""

import copy
import dataclasses

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
