"""Start-up: each engine imports only what it uses, and MJX's batch function is traced once per
configuration across processes (stored with `jax.export`), never run stale."""

import os

import jax
import numpy as np

import simloader
from simloader import controls, models
from simloader.backends.mjx import stored_program

IMPORTS = """
import sys, simloader
ds = simloader.SimDataset("cartpole", backend={backend!r}, nbatch=4, nstep=3, num_batches=1,
                          control=simloader.controls.Uniform(){extra})
next(iter(ds))
print(sorted({{m.split(".")[0] for m in sys.modules}} & {{"jax", "jaxlib", "warp",
                                                        "mujoco_warp"}}))
"""


def test_each_engine_imports_only_what_it_uses(fresh_python):
    rollout, jax_dataset = fresh_python(
        IMPORTS.format(backend="cpu", extra=", nthread=1"),
        [([], {})]) + fresh_python(
        IMPORTS.format(backend="mjx", extra=", compilation_cache=False"), [([], {})])
    assert rollout.split("\n")[-2] == "[]"  # no JAX, no Warp for MuJoCo on CPU threads
    # MJX on JAX without Warp (MJX's optional Warp support stays unimported)
    assert jax_dataset.split("\n")[-2] == "['jax', 'jaxlib']"


def test_import_and_version_load_neither_torch_nor_mujoco(fresh_python):
    # `simloader --version` answered in about 0.1 s where importing everything took 2.2 s
    out, = fresh_python("""
import sys, simloader
from simloader import launch
launch.main(["--version"])
print(sorted({m.split(".")[0] for m in sys.modules} & {"torch", "mujoco", "numpy"}))
print(simloader.SimDataset.__name__, simloader.store.formats.__name__)
""", [([], {})])
    lines = out.split("\n")
    assert lines[-4:-1] == [f"simloader {simloader.__version__}", "[]",
                            "SimDataset simloader.store.formats"]


# one process's first batch: the traces of the batch function, what was loaded, a digest of
# the delivered arrays
FIRST_BATCH = """
import hashlib, sys, jax
import simloader
timestep, low = float(sys.argv[2]), float(sys.argv[3])
model = simloader.models.load_model("cartpole")
model.opt.timestep = timestep
traced = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: traced.append(1)
    if event == "/jax/core/compile/jaxpr_trace_duration" and kw.get("fun_name") == "simulate"
    else None)
ds = simloader.SimDataset(model, backend="mjx", nbatch=8, nstep=10, seed=1,
                          control=simloader.controls.Uniform(low=low, high=1.0),
                          compilation_cache=sys.argv[1])
batch = next(iter(ds))
digest = hashlib.sha256(b"".join(batch[k].numpy().tobytes() for k in sorted(batch)
                                 if hasattr(batch[k], "numpy"))).hexdigest()[:16]
print(len(traced), ds.stats["traces"], ds.stats["programs_loaded"], digest)
"""


def test_a_second_process_loads_the_program_and_a_changed_one_traces_again(fresh_python,
                                                                          tmp_path):
    cache = str(tmp_path / "cache")
    cold, = fresh_python(FIRST_BATCH, [([cache, 0.01, -1.0], {})])
    assert cold.split()[:3] == ["1", "1", "0"]  # traced, stored
    assert len(os.listdir(os.path.join(cache, stored_program.FOLDER))) == 2  # + compile times
    # warm: the same configuration; a changed model (that every other part of the
    # configuration enters the key is checked in-process, by the next test)
    warm, changed = fresh_python(FIRST_BATCH, [([cache, 0.01, -1.0], {}),
                                               ([cache, 0.005, -1.0], {})])
    assert warm.split()[:3] == ["0", "0", "1"]  # not traced: loaded
    assert warm.split()[3] == cold.split()[3]  # the same batch, bit for bit
    assert changed.split()[:3] == ["1", "1", "0"], changed  # a stale program never runs
    assert changed.split()[3] != cold.split()[3]


def _dataset(cache, **kwargs):
    args = dict(backend="mjx", nbatch=4, nstep=5, seed=0, num_batches=1,
                control=controls.Uniform(), compilation_cache=cache)
    args.update(kwargs)
    return simloader.SimDataset(args.pop("model", "cartpole"), **args)


def test_program_key_covers_what_the_program_is_made_of(monkeypatch):
    device = jax.devices()[0]
    leaves = [np.zeros((4, 3), np.float32)]
    ds = _dataset(False)
    key = stored_program.key(ds.config, device, leaves)
    # what enters as arguments shares the program
    assert stored_program.key(_dataset(False, seed=5, num_batches=3).config, device,
                              leaves) == key
    model = models.load_model("cartpole")
    model.dof_damping[:] += 0.1
    changed = {
        "model": _dataset(False, model=model),
        "sizes": _dataset(False, nbatch=8),
        "record": _dataset(False, record=("state", "qacc")),
    }
    for what, other in changed.items():
        assert stored_program.key(other.config, device, leaves) != key, what
    assert stored_program.key(ds.config, device, [np.zeros((4, 3), np.float64)]) != key
    monkeypatch.setattr(stored_program, "source_digest", lambda: "edited")
    assert stored_program.key(ds.config, device, leaves) != key  # another simloader source
    monkeypatch.undo()
    real = stored_program._version
    monkeypatch.setattr(stored_program, "_version",
                        lambda name: "9.9" if name == "jax" else real(name))
    assert stored_program.key(ds.config, device, leaves) != key  # another JAX


def test_a_cold_compile_says_so_and_an_unreadable_stored_program_is_traced_again(tmp_path,
                                                                                 capfd):
    cache = str(tmp_path)
    first = next(iter(_dataset(cache)))
    said = capfd.readouterr().err
    assert "simloader: tracing and compiling the batch function (4 x 5, MJX-JAX on cpu)" in said
    assert "the last one took" not in said and "done in" in said
    folder = os.path.join(cache, stored_program.FOLDER)
    stored, = [f for f in os.listdir(folder) if f.endswith(stored_program.SUFFIX)]
    with open(os.path.join(folder, stored), "r+b") as f:
        f.truncate(100)  # a file cut short (a full disk, a killed copy)
    ds = _dataset(cache)
    again = next(iter(ds))
    said = capfd.readouterr().err
    assert "ignoring the stored program" in said
    # the progress line now says how long this model's last compilation took
    assert "(4 x 5, MJX-JAX on cpu) (the last one took" in said
    assert ds.stats["traces"] == 1 and ds.stats["programs_loaded"] == 0
    np.testing.assert_array_equal(again["state"].numpy(), first["state"].numpy())
    ds = _dataset(cache)  # replaced: loads again
    np.testing.assert_array_equal(next(iter(ds))["state"].numpy(), first["state"].numpy())
    assert ds.stats["traces"] == 0 and ds.stats["programs_loaded"] == 1


def test_without_compilation_cache_nothing_is_stored(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    ds = _dataset(False)
    next(iter(ds))
    assert ds.stats["traces"] == 1 and not any(tmp_path.rglob("*" + stored_program.SUFFIX))


def test_construction_puts_the_model_once(monkeypatch):
    from simloader.backends.mjx import pool, program
    calls = []
    real = pool.put_models
    monkeypatch.setattr(program, "put_models",
                        lambda *a: calls.append(1) or real(*a))
    ds = _dataset(False)
    next(iter(ds))
    assert calls == [1]  # by the checks at construction; the program reuses it


def test_without_flatbuffers_the_dataset_runs_and_says_why_nothing_is_kept(tmp_path, monkeypatch,
                                                                          capfd):
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "flatbuffers" else real(name, *a))
    stored_program._missing_once.cache_clear()
    ds = _dataset(str(tmp_path))
    next(iter(ds))
    assert ds.stats["traces"] == 1 and not any(tmp_path.rglob("*" + stored_program.SUFFIX))
    assert "jax.export needs the flatbuffers package" in capfd.readouterr().err
