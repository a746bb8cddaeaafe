"""Binding an engine to validated settings, once: the one place construction meets the
registry.

`bind` takes `SimDataset`'s `backend` word, its engine keyword options and the engine-free
`config.Settings` (with one per simulation device for `sim_device=`), and in one pass:
spells the word in today's vocabulary, lets the engines make their process-wide settings,
chooses the engine (`auto`), asks it whether it can be deterministic for the model (a
question: the flag that makes it so is set where its runtime starts), refuses `sim_device`
for an engine that simulates on no device of its own, checks the sizes and resolves the
options. It returns a `BoundEngine`: the engine and the complete `SimConfig`, which the
dataset holds and calls directly.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Any, Optional

from simloader import layout, sharding
from simloader.backends import (ENGINES, all_options, auto, engine, engine_options, prepare,
                                spelled)
from simloader.backends.base import Backend, Stats
from simloader.backends.contract import Engine
from simloader.config import Settings, SimConfig


@dataclasses.dataclass(frozen=True)
class BoundEngine:
    """An engine bound to a dataset's configuration.

    Attributes:
      engine: the registry's entry (`backends.contract.Engine`).
      config: the complete configuration it simulates.
    """

    engine: Engine
    config: SimConfig

    @property
    def name(self) -> str:
        return self.config.backend

    @property
    def counters(self) -> tuple[str, ...]:
        return tuple(self.engine.counters)

    @property
    def forks_safely(self) -> bool:
        """Whether a DataLoader worker forked from this process may run it (no GPU runtime,
        no JAX)."""
        device = self.config.device
        return self.engine.forks_safely and (device is None or device.type == "cpu")

    def create(self, shard: sharding.Shard, stats: Stats) -> Backend:
        """Its backend for one shard (simulating on other devices than it delivers to:
        `split.SplitBackend`)."""
        if self.config.parts is not None:
            from simloader.backends.split import SplitBackend
            return SplitBackend(self.config, shard, stats, self.engine.create)
        return self.engine.create(self.config, shard, stats)


def check_keywords(options: dict[str, Any], own: Iterable[str]) -> None:
    """Refuses an unknown keyword that is a typo of one of `own` (SimDataset's keywords; they
    would end in `**backend_options`), with a did-you-mean; other unknown ones the engine
    refuses when it is bound, listing its options."""
    names = list(own) + list(all_options())
    unknown = sorted(k for k in options if k not in all_options())
    hints = {k: layout.did_you_mean(k, names) for k in unknown}
    if any(hints.values()):
        said = "; ".join(f"{k!r}{h or ' (no close match)'}" for k, h in hints.items())
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {unknown}: {said}")


def accepting(model: Any, refused_by: str) -> str:
    """Which other engines simulate `model` here, as advice ("use backend='cpu'")."""
    names = [name for name in ENGINES if name != refused_by
             and engine(name).missing() is None and engine(name).refuses_model(model) is None]
    return ("use " + " or ".join(f"backend={n!r}" for n in names) + ", which simulate"
            + ("s" if len(names) == 1 else "") + " it") if names else "no engine here does"


def bind(backend: Any, options: dict[str, Any], settings: Settings,
         parts: Optional[tuple[Settings, ...]] = None) -> BoundEngine:
    """The engine for `settings` (see the module's docstring).

    Raises:
      TypeError, ValueError: a `backend` word or an option no engine takes; no engine can run
        here; the engine cannot be deterministic for the model, simulate on `sim_device`, or
        hold the batch; an option the engine refuses.
    """
    name, options, gpu_only = spelled(backend, options)
    prepare(name, options)
    choice = auto.choose(name, gpu_only or parts is not None, settings)
    entry = engine(choice.backend)
    if choice.reason == "asked":
        refusal = entry.refuses_model(settings.model)
        if refusal is not None:
            raise ValueError(f"backend: {choice.backend!r} cannot simulate this model: "
                             f"{refusal}; {accepting(settings.model, choice.backend)}")
    if settings.deterministic:
        refusal = entry.refuses_determinism(settings.model)
        if refusal is not None:
            raise ValueError(f"deterministic: backend={choice.backend!r} cannot give "
                             f"bit-identical batches for this model: {refusal}")
    refusal = entry.refuses_sim_device() if parts is not None else None
    if refusal is not None:
        raise ValueError(f"sim_device: {refusal}")
    own = _own_options(entry, options, choice.reason)
    engine_fields = dict(backend=choice.backend, backend_reason=choice.reason)
    entry.check_sizes(settings)
    if parts is None:
        options_ = entry.check_options(settings, own, choice.reason)
        return BoundEngine(entry, SimConfig.bound(settings, options=options_, **engine_fields))
    configs = []
    for part in parts:
        entry.check_sizes(part)
        configs.append(SimConfig.bound(part, options=entry.check_options(part, own,
                                                                         choice.reason),
                                       **engine_fields))
    # the engine's options as each part resolved them on its device (the first one's reported)
    return BoundEngine(entry, SimConfig.bound(settings, options=configs[0].options,
                                              parts=tuple(configs), **engine_fields))


def _own_options(entry: Engine, options: dict[str, Any], reason: str) -> dict[str, Any]:
    """The keyword options of `entry`'s; another engine's is refused when the engine was
    asked by name, and left unused when `auto` chose it (the user may not know which engine
    runs); one no engine takes, always.

    Raises:
      TypeError: an option of another engine, or of none, naming this engine's options.
    """
    mine = tuple(entry.options)
    unknown = sorted(set(options) - set(mine))
    if not unknown:
        return dict(options)
    asked = "auto" not in reason
    if asked or any(name not in all_options() for name in unknown):
        owners = [f"{n!r} is an option of backend={e!r}" for n in unknown
                  for e, names in engine_options().items() if n in names]
        raise TypeError(f"SimDataset: unexpected keyword argument(s) {unknown} for "
                        f"backend={entry.name!r} (its options are {list(mine)})"
                        + "".join(f"; {o}" for o in owners))
    return {k: v for k, v in options.items() if k in mine}
