"""Process-wide concerns of the Warp engine: whether it can run, on which device, importing
Warp quietly, and the one lock under which engines queue Warp work.

Nothing here imports JAX: a Warp dataset never starts it. Nothing here initializes CUDA at
construction either (the checks look for packages and devices only), so that the process that
builds a dataset can still fork.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from typing import Any, Optional

import torch

# MuJoCo Warp on the CPU (Warp's LLVM backend) is slow and not offered to users; the test suite
# sets this to run the Warp engine for real on machines without a GPU
WARP_ON_CPU = "SIMLOADER_WARP_ON_CPU"
# what to install for backend="warp"
INSTALL = "pip install 'simloader[warp]'"

# Held whenever simloader scopes a Warp device or stream: an engine's build (allocations, the
# first step, the graph capture), each of its batches, its release, and the CPU model a
# dataset's checks put. Warp's current device and stream belong to the process, not to a
# thread (`ScopedDevice`, `Device.set_stream`), and MuJoCo Warp launches and allocates on
# them. Unlocked, a dataset checked in one thread while another thread's engine was built sent
# that engine's kernels to Warp's CPU device (an H200 run compiling CPU kernels mid-run, in
# 3 of 4 runs of tests/test_warp_gpu.py's engine-built-while-another-queues test); two threads
# scoping their engines' streams at once would send kernels to the other's stream or past a
# capture. Queuing is asynchronous: the lock is held for host time, not while the GPU works.
WARP_LOCK = threading.RLock()


def missing() -> Optional[str]:
    """Why the Warp engine cannot run in this process (short), or None when it can."""
    for module, package in (("warp", "warp-lang"), ("mujoco_warp", "mujoco-warp")):
        try:
            found = importlib.util.find_spec(module) is not None
        except ValueError:  # in sys.modules as None: import blocked
            found = False
        if not found:
            return f"the {package} package is not installed ({INSTALL})"
    if torch.cuda.is_available() or os.environ.get(WARP_ON_CPU) == "1":
        return None
    return "MuJoCo Warp needs a CUDA GPU, and torch sees none here"


def sim_device(target: Optional[torch.device]) -> torch.device:
    """Where to simulate: `cuda:k` for a `cuda:k` target (no copy at delivery), else this local
    rank's GPU (torchrun's LOCAL_RANK), else the CPU (only with SIMLOADER_WARP_ON_CPU=1)."""
    if not torch.cuda.is_available():
        return torch.device("cpu")
    if target is not None and target.type == "cuda":  # an index torch sees (build_config)
        index = target.index if target.index is not None else torch.cuda.current_device()
        return torch.device("cuda", index)
    return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0"))
                        % torch.cuda.device_count())


def warp() -> Any:
    """The `warp` module, initialized without its banner."""
    import warp as wp
    wp.config.quiet = True
    # no line per kernel module loaded (the engine says when a first compile takes long)
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.init()
    return wp


def warp_device(device: torch.device) -> str:
    """Warp's name of a torch device."""
    return "cpu" if device.type == "cpu" else f"cuda:{device.index}"
