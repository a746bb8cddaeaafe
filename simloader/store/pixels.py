"""Pixels from stored states: a store of states renders its cameras on read.

A frame is a pure function of the state and the model, so a store that keeps the states
(`record=("state",)`) needs no images: `StoredDataset(path, cameras=...)` renders them when an
item or a transitions batch is read, with the model the writer simulated (kept in the store's
`provenance/models/`, one MJB file per model of its pool: the model, the model list or the
structural variants) and each trajectory's stored randomized values (`params/...`) written into
it, as the CPU engine's own cameras render each trajectory with its own model.

The CPU renderer draws exactly what a streamed `Camera` of the CPU engine drew: the engine
renders each frame's `mjSTATE_INTEGRATION` row after `mj_forward`; here the row is made from the
stored `mjSTATE_FULLPHYSICS` state (every input a scene shows, mocap poses and equality
activations, is part of it; the others, controls and applied forces, as `mj_resetData` leaves
them, do not change the picture), then drawn by the same code (`simloader.render`). Renderers
are made per process and thread at the first read, so DataLoader workers render in parallel.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from typing import Any, Optional

import mujoco
import numpy as np

from simloader import identity, layout, records, render
from simloader import randomize as dr

MODELS = "provenance/models"  # the pool's MJB files: 0.mjb.zlib, 1.mjb.zlib, ...
MJB_COMPRESSED = ".mjb.zlib"


def save_models(folder: Any, pool: Sequence[mujoco.MjModel]) -> None:
    """The writer's pool of models (`pool_of`), as MJB files (the compiled models, bit for
    bit), compressed with zlib (`MJB_COMPRESSED`): a small model's file is mostly its
    textures (dm_control's skybox: 11.8 MB of a 12.7 MB walker store), which compress
    about 17x. `folder`: the store's `StoreFolder`."""
    # a zarr group (with files of its own beside): zarr readers see it as the store's
    folder.write_json(MODELS + "/zarr.json", {
        "zarr_format": 3, "node_type": "group",
        "attributes": {"files": "MJB models, zlib-compressed (NAME.mjb.zlib)"}},
        durable=True)
    for k, model in enumerate(pool):
        buffer = np.empty(mujoco.mj_sizeModel(model), dtype=np.uint8)
        mujoco.mj_saveModel(model, None, buffer)
        folder.write(f"{MODELS}/{k}{MJB_COMPRESSED}", [zlib.compress(buffer, 6)],
                     durable=True)
    folder.sync([MODELS, "provenance"])


def load_models(stored: Any, count: int) -> list[mujoco.MjModel]:
    """The store's kept models (`save_models`; a store written before they were compressed
    keeps plain `K.mjb` files), read through its folder: a missing, linked or damaged file is
    refused naming it."""
    pool = []
    for k in range(count):
        compressed, plain = f"{MODELS}/{k}{MJB_COMPRESSED}", f"{MODELS}/{k}.mjb"
        name = plain if stored.folder.kind(compressed) is None and \
            stored.folder.kind(plain) is not None else compressed
        where = stored.folder.where(name)
        try:
            data = stored.folder.read(name, 1 << 31)
            if name == compressed:
                data = zlib.decompress(data)
            # from memory, as an asset of that name: no file outside the store is made
            pool.append(mujoco.MjModel.from_binary_path("model.mjb", {"model.mjb": data}))
        except FileNotFoundError:
            raise ValueError(f"cameras: the store's model {where} is missing (removed?); "
                             f"pass model= (the model that wrote it)") from None
        except (OSError, ValueError, zlib.error) as e:
            raise ValueError(f"cameras: the store's model {where} cannot be read ({e}); it "
                             f"is damaged or not an MJB file simloader wrote: pass model= "
                             f"(the model that wrote it)") from None
    return pool


def kept_models(stored: Any) -> Optional[list[mujoco.MjModel]]:
    """The store's pool of models as kept, or None where it kept none or they cannot be
    read (what asks can do without them: `known_faults.stored_warning`)."""
    try:
        return load_models(stored, _count(stored))
    except ValueError:
        return None


def _count(stored: Any) -> int:
    """How many models the store kept, from its root (`ValueError` where the entry is not
    one `save_models` writes)."""
    kept = stored.info.get("models")
    count = kept.get("count") if isinstance(kept, dict) else None
    if not isinstance(kept, dict) or kept.get("kind") not in ("model", "models", "variants") or \
            not isinstance(count, int) or isinstance(count, bool) or \
            not 1 <= count <= 1 << 16 or (kept["kind"] == "variants" and count < 2):
        raise ValueError(f"cameras: the store at {stored.path!r} says its models are "
                         f"{kept!r} (expected kind 'model' with count 1, 'models' with one "
                         f"per batch row, or 'variants' with the base model and at least one "
                         f"variant): its root was edited or damaged; pass model=")
    return count


class StoredCameras:
    """The cameras a `StoredDataset` renders on read, checked against its store at
    construction: the model (from the store, or `model=` checked against the store's
    digest), the camera names, the stored keys rendering needs, and the engine that renders
    (`backends.stored_renderer`: `backend="auto"` takes the CPU renderer on the host and
    MuJoCo Warp's on a CUDA `device`)."""

    def __init__(self, stored: Any, cameras: Any, backend: str = "auto",
                 device: Any = None, model: Any = None):
        from simloader import backends
        self.stored = stored
        self.pool, self.kind = _models(stored, model)
        base = self.pool[0]
        asked = [cameras] if isinstance(cameras, records.Camera) else (
            list(cameras) if isinstance(cameras, (list, tuple)) else None)
        if not asked or not all(isinstance(c, records.Camera) for c in asked):
            raise TypeError(f"cameras: expected a simloader.Camera or a sequence of them, got "
                            f"{cameras!r}")
        images = []
        for camera in asked:
            try:
                images += records.camera_images(base, camera)
            except ValueError as e:
                raise ValueError(f"cameras: {str(e).removeprefix('record: ')}") from None
        self.images = tuple(images)
        self.keys = [o.key for o in images]
        nstate = mujoco.mj_stateSize(base, layout.FULLPHYSICS)
        if "state" not in stored.layouts:
            raise ValueError(
                f"cameras: rendering needs every frame's positions (and mocap poses), and the "
                f"store at {stored.path!r} has no 'state' (it holds {sorted(stored.layouts)}); "
                f"write it with record=(\"state\",) (simloader write --record state)")
        width = stored.layouts["state"].trailing[-1]
        if width != nstate:
            raise ValueError(f"model: its mjSTATE_FULLPHYSICS state has {nstate} columns, the "
                             f"store's 'state' {width}: not the store's model")
        self.plan = _plan(stored, base)
        self.params = [k for k in stored.layouts if k.startswith("params/")]
        randomized = self.kind != "model" or self.plan is not None
        self.renderer = backends.stored_renderer(backend, base, self.images, device,
                                                 randomized)

    def frames(self, states: np.ndarray, trajectories: np.ndarray) -> dict[str, Any]:
        """{image key: (n, nframes, *image shape) tensor} of `states` ((n, nframes, nstate)
        FULLPHYSICS rows of stored trajectories `trajectories`)."""
        return self.renderer.frames(states, self._model_of(np.asarray(trajectories)))

    def _model_of(self, trajectories: np.ndarray) -> Any:
        """Stored trajectory `trajectories[i]`'s model as it ran (`render.model_of`, as the
        CPU engine's streamed cameras find it): its batch row's of a model list, its
        variant, or the model with its randomized values written in."""
        stored = self.stored
        rows = trajectories % stored.nbatch
        params = ({} if self.kind == "models" or self.plan is None and self.kind == "model"
                  else {k[len("params/"):]: np.stack([stored.read(int(t), [k])[k]
                                                      for t in trajectories])
                        for k in self.params})
        # the pool: the model; one model per batch row; or the base model, then each variant
        return render.ModelPool(
            self.pool[0], randomization=self.plan,
            models=[self.pool[int(r)] for r in rows] if self.kind == "models" else None,
            variants=self.pool[1:] if self.kind == "variants" else None).model_of(params)


def pool_of(config: Any) -> tuple[str, list[mujoco.MjModel]]:
    """What a store keeps of a configuration's models, and its kind: "model" (the one),
    "models" (one per batch row) or "variants" (the base model, then each variant)."""
    if config.models:
        return "models", list(config.models)
    if config.variants:
        return "variants", [config.model, *config.variants]
    return "model", [config.model]


def _models(stored: Any, model: Any) -> tuple[list[mujoco.MjModel], str]:
    """The store's pool of models (or `model=`), checked against the store's digests."""
    kept = stored.info.get("models")
    if model is not None:
        from simloader.models import load_model
        pool = (list(model) if isinstance(model, (list, tuple)) else
                [model if isinstance(model, mujoco.MjModel) else load_model(model)])
        pool = [m if isinstance(m, mujoco.MjModel) else load_model(m) for m in pool]
        kind = kept["kind"] if isinstance(kept, dict) else _kind(stored, pool)
        _check(stored, pool, kind, "model: not the model(s) the store at "
                                   f"{stored.path!r} was simulated with")
        return pool, kind
    if not isinstance(kept, dict):
        raise ValueError(f"cameras: the store at {stored.path!r} was written before simloader "
                         f"kept the model in its stores: pass the model that wrote it, "
                         f"model= (a name, an MJCF path or an MjModel; the list of a "
                         f"models= stream; checked against the store's digest)")
    pool = load_models(stored, _count(stored))
    _check(stored, pool, kept["kind"], f"cameras: the store's model files in "
                                        f"{stored.folder.where(MODELS)} do not match its "
                                        f"digests (edited?); pass model=")
    return pool, kept["kind"]


def _kind(stored: Any, pool: list) -> str:
    """The kind of pool a store written before it kept its models had, from its
    fingerprint: structural variants, a model list, or one model."""
    randomize = stored.info["fingerprint"].get("randomize")
    if isinstance(randomize, dict) and "variants" in randomize:
        return "variants"
    return "models" if len(pool) > 1 else "model"


def _check(stored: Any, pool: list, kind: str, refusal: str) -> None:
    """The pool's digests are the fingerprint's: the model (the base model of variants, or
    the whole list of a model list), and each variant's."""
    fp = stored.info["fingerprint"]
    simulated = pool[:1] if kind != "models" else pool
    wanted = fp["model"]
    if _digest(simulated) != wanted:
        raise ValueError(f"{refusal} (digest {_digest(simulated)}, the store's {wanted})")
    if kind == "variants":
        variants = [identity.model_digest(m) for m in pool[1:]]
        if variants != list(fp["randomize"]["variants"]):
            raise ValueError(f"{refusal}: its structural variants differ (pass the base model "
                             f"and then every variant, in order)")
    if kind == "models" and len(pool) != stored.nbatch:
        raise ValueError(f"{refusal}: a models= store takes one model per batch row "
                         f"({stored.nbatch}), got {len(pool)}")


def _digest(models: Sequence[mujoco.MjModel]) -> str:
    import hashlib
    return hashlib.sha256("".join(identity.model_digest(m) for m in models).encode()
                          ).hexdigest()[:16]


def _plan(stored: Any, model: mujoco.MjModel) -> Optional[dr.RandomizationPlan]:
    """The randomization the writer applied, rebuilt from the store's fingerprint (which
    fields of which objects each stored `params/KEY` holds); None without one."""
    spec = stored.info["fingerprint"].get("randomize")
    if not isinstance(spec, list):
        return None
    params = []
    for p in spec:
        params.append(dr.Param(p["field"], dr.Uniform(0, 0), p["op"], p["on"],
                               index=p.get("index"), shared=p.get("shared", False),
                               name=p.get("name")))
    plan = dr.RandomizationPlan(model, params)
    missing = [r.param.key for r in plan.resolved
               if "params/" + r.param.key not in stored.layouts]
    if missing:
        raise ValueError(f"cameras: the store lacks the randomized values {missing} its "
                         f"trajectories were simulated with; rendering would draw another "
                         f"model")
    return plan
