"""Two torch.distributed ranks on localhost (gloo, CPU): distinct streams, clean shutdown."""

import json
import pathlib
import socket
import subprocess
import sys
import threading

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import simloader


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_main(rank: int, world: int, port: int, results) -> None:
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank,
                            world_size=world)
    try:
        ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=5,
                                  control=simloader.controls.Uniform(), num_batches=3, seed=7)
        loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2)
        controls = torch.stack([b["control"] for b in loader])
        gathered = [None] * world
        dist.all_gather_object(gathered, controls)
        threads = [t.name for t in threading.enumerate() if t.name == "simloader-prefetch"]
        results[rank] = (gathered, threads, len(controls))
    finally:
        dist.destroy_process_group()


@pytest.mark.skipif(not dist.is_available(), reason="torch.distributed unavailable")
def test_two_ranks_draw_distinct_streams():
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager:
        results = manager.dict()
        port = _free_port()
        procs = [ctx.Process(target=_rank_main, args=(r, 2, port, results)) for r in range(2)]
        for p in procs:
            p.start()
        for p in procs:
            p.join(timeout=240)
        assert all(p.exitcode == 0 for p in procs), [p.exitcode for p in procs]
        results = dict(results)
    gathered, threads, count = results[0]
    assert count == 3  # num_batches is per rank
    assert threads == [] and results[1][1] == []  # no producer left behind
    rows = torch.cat([g.flatten(0, 1).flatten(1) for g in gathered])  # every trajectory's controls
    assert len(torch.unique(rows, dim=0)) == len(rows) == 2 * 3 * 4


def _run_ddp_example(result_file, env):
    root = pathlib.Path(__file__).parents[1]
    return subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         str(root / "examples" / "train_world_model_ddp.py"), "--quick", "--backend", "cpu",
         "--json", str(result_file)],
        capture_output=True, text=True, timeout=300, cwd=root, env=env)


def test_ddp_example_under_torchrun(tmp_path, checkout_env):
    """The DDP example as a user launches it: torchrun, two ranks, gloo on the CPU."""
    result_file = tmp_path / "result.json"
    proc = _run_ddp_example(result_file, checkout_env())
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    assert "terminate called" not in proc.stderr, proc.stderr[-4000:]
    result = json.loads(result_file.read_text())
    assert result["ranks"] == 2 and result["steps_per_s"] > 0
    assert "open-loop RMSE" in proc.stdout


def _ddp_example_exits_zero(tmp_path, env, runs):
    """Runs the DDP example `runs` times: every run must exit 0 (a rank that aborts at exit,
    "terminate called without an active exception", fails the job under torchrun)."""
    failures = []
    for i in range(runs):
        proc = _run_ddp_example(tmp_path / f"result{i}.json", env)
        if proc.returncode != 0 or "terminate called" in proc.stderr:
            failures.append(f"run {i}: exit {proc.returncode}\n{proc.stderr[-3000:]}")
    assert not failures, f"{len(failures)} of {runs} runs failed:\n" + "\n".join(failures)


@pytest.mark.slow
def test_ddp_example_exits_zero_20_times(tmp_path, checkout_env):
    _ddp_example_exits_zero(tmp_path, checkout_env(), runs=20)


_EXIT_SCRIPT = """
import sys
import torch
import simloader
how, nthread = sys.argv[1], int(sys.argv[2])
ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=16, nstep=20, seed=0,
                          nthread=nthread, control=simloader.controls.Uniform())
if how == "open":  # an iterator left open at exit, its producer simulating ahead
    it = iter(ds)
    next(it)
elif how == "break":  # broke out of the loop
    for i, batch in enumerate(ds):
        if i == 2:
            break
elif how == "loader":  # a DataLoader's iterator left open
    it = iter(torch.utils.data.DataLoader(ds, batch_size=None))
    next(it)
elif how == "finished":
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=16, nstep=20, seed=0,
                              nthread=nthread, num_batches=3)
    assert len(list(ds)) == 3
print("done")
"""


@pytest.mark.parametrize("how", ["open", "break", "loader", "finished"])
def test_rollout_script_exits_zero_however_the_stream_ends(how, checkout_env):
    # the native thread pool (nthread=2) and the producer must be gone before teardown; two
    # runs at once (an abort at exit was intermittent)
    procs = [subprocess.Popen([sys.executable, "-c", _EXIT_SCRIPT, how, "2"], text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=checkout_env())
             for _ in range(2)]
    for proc in procs:
        stdout, stderr = proc.communicate(timeout=120)
        assert proc.returncode == 0, stderr[-4000:]
        assert stdout.strip() == "done", stdout
        assert "terminate called" not in stderr and "Traceback" not in stderr, stderr
        assert "Exception ignored" not in stderr, stderr


_RANK_DEVICE_SCRIPT = """
import json, os
import simloader
# MJX starts JAX: it must do so with simloader's settings (no preallocation)
ds = simloader.SimDataset("cartpole", backend="mjx", nbatch=4, nstep=3, num_batches=1, seed=0)
import jax
batch = next(iter(ds))
print(json.dumps({
    "preallocate": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE"),
    "jax_gpus": sorted({d.local_hardware_id for a in jax.live_arrays() for d in a.devices()}),
    "tensor": str(batch["state"].device), "rank": os.environ["LOCAL_RANK"]}))
"""


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available() or torch.cuda.device_count() < 2,
                    reason="needs 2 GPUs")
def test_torchrun_ranks_simulate_on_their_own_gpu(tmp_path, checkout_env):
    script = tmp_path / "rank.py"
    script.write_text(_RANK_DEVICE_SCRIPT)
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
         str(script)], capture_output=True, text=True, timeout=300, env=checkout_env())
    assert proc.returncode == 0, proc.stderr[-4000:]
    results = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(results) == 2
    for r in results:  # JAX's buffers live on the rank's GPU, and the tensors too
        assert r["jax_gpus"] == [int(r["rank"])], r
        assert r["tensor"] == f"cuda:{r['rank']}", r
        assert r["preallocate"] == "false", r


def test_scale_out_script_on_cpu_ranks(checkout_env):
    """benchmarks/scale_out.py as the GPU machines run it, here two CPU ranks (gloo): each
    rank's stream distinct and reproducible from its seed, one store written by both."""
    root = pathlib.Path(__file__).parents[1]
    out = subprocess.run([sys.executable, str(root / "benchmarks" / "scale_out.py"), "--quick",
                          "--engines", "cpu", "--modes", "open", "write", "--nprocs", "2",
                          "--batches", "2"],
                         capture_output=True, text=True, timeout=300, cwd=root,
                         env=checkout_env())
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    rows = [line for line in out.stdout.splitlines() if line.startswith("| cpu")]
    assert len(rows) == 2, out.stdout
    # the ranks' streams distinct, and each rank's first batch simulated again bit for bit
    cells = [[c.strip() for c in row.split("|")] for row in rows]
    assert all("yes" in c and any(x.startswith("bit-equal") for x in c) for c in cells), rows
    assert "256 stored, ranks [0, 1]" in rows[1], rows[1]


@pytest.mark.slow  # 40 s on 2 cores: the suite's time; test_scale_out_script_on_cpu_ranks runs it
def test_scale_out_interleaves_layouts_and_repeats(checkout_env):
    """`--nodes 1 2 --repeats 2`: every layout (one node of 2 ranks, two nodes of 1, and the
    1-rank reference) runs twice, interleaved; a row gives the median and each repeat's ratio
    to the reference job of the same repeat."""
    root = pathlib.Path(__file__).parents[1]
    out = subprocess.run([sys.executable, str(root / "benchmarks" / "scale_out.py"), "--quick",
                          "--engines", "cpu", "--modes", "open", "--nprocs", "1", "2",
                          "--nodes", "1", "2", "--repeats", "2", "--batches", "1"],
                         capture_output=True, text=True, timeout=400, cwd=root,
                         env=checkout_env())
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    # jobs in the order they ran: all layouts, then all again
    ran = [line.split(":")[0] for line in out.stdout.splitlines() if ": per rank " in line]
    layouts = ["cpu/open, 1 rank(s), 1 node(s)", "cpu/open, 2 rank(s), 1 node(s)",
               "cpu/open, 2 rank(s), 2 node(s)"]
    assert ran == layouts * 2, ran
    rows = [[c.strip() for c in line.split("|")[1:-1]]
            for line in out.stdout.splitlines() if line.startswith("| cpu")]
    assert [(r[3], r[4]) for r in rows] == [("1", "1"), ("1", "2"), ("2", "2")], rows
    assert rows[0][9] == "1.00x, 1.00x", rows[0]
    for r in rows:
        assert len(r[9].split(", ")) == 2 and r[10] == "yes" and r[11] == "bit-equal", r
