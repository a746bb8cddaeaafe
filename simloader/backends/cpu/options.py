"""The CPU backend's checks at construction: what `mujoco.batch` on CPU threads cannot do, or
needs (an OpenGL platform for cameras), refused by name."""

from __future__ import annotations

import dataclasses
from typing import Any

from simloader import memory
from simloader import render


@dataclasses.dataclass(frozen=True)
class CpuOptions:
    """The CPU engine's resolved options: none of its own (fields would enter the resume
    fingerprint)."""

    def simulated_by(self) -> str:
        return "mujoco.batch on CPU threads"


def check_options(config: Any, options: dict[str, Any], reason: str = "") -> CpuOptions:
    """Validates a `backend="cpu"` configuration (it takes no options of its own;
    `reason`, why this engine was chosen, is the registry's common argument).

    Raises:
      TypeError: any option (`options` must be empty).
      ValueError: cameras this backend cannot render, no working OpenGL, or a policy that
        would see cameras (rendered after the batch, too late for it).
    """
    if options:
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {sorted(options)} for "
                        f"backend='cpu'")
    images = [o for o in config.observations if o.rendered]
    if not images:
        return CpuOptions()
    if config.policy is not None:
        raise ValueError("policy, record: on backend='cpu' a policy cannot see cameras yet "
                         "(they are rendered after the batch); use backend='warp' (MuJoCo Warp "
                         "renders every step), or record no Camera")
    render.check(config.model, images)
    render.gl_platform()  # fails here, naming what to install, if no GL works
    return CpuOptions()


def check_sizes(sizes: Any) -> None:
    """Refuses a batch whose copies in flight (the prefetched ones and the one being simulated)
    cannot fit in host memory, from its sizes alone (`config.build_config` calls it before the
    tables are built).

    Raises:
      ValueError: naming `nbatch` and `record`, with the size and what is available.
    """
    memory.check_batch_fits(sizes, memory.host_available(), "host memory",
                             count=sizes.prefetch + 1)
