"""OpenGL rendering on the CPU: a pool of `mujoco.Renderer`s, one set per thread, for the CPU
engine's cameras and for `simloader.video`.

The simulation records, per frame, the `mjSTATE_INTEGRATION` rows of the trajectories (the
physics state and every input a scene shows: mocap poses, equality activations); the pool then
renders each recorded state as a plain `mujoco.Renderer` would after `mj_forward` of that
state, straight into the batch's image tensors, while the prefetch thread simulates the next
batch. Each trajectory is rendered with its own model (model lists, variants, randomized
colours, lights or cameras), so the pixels equal `mujoco.Renderer(model_i).update_scene(d,
camera)` bit for bit.

OpenGL contexts belong to the thread that made them current, so every render thread makes its
renderers once and keeps them. Nothing of GL is initialized before the first render (the
probe runs in a child process), so a dataset made in a trainer works in forked DataLoader
workers. The GL platform: `MUJOCO_GL` where set (as MuJoCo reads it); else EGL (a GPU's
driver, or Mesa's software rasterizer on a CPU-only machine), else OSMesa.
"""

from __future__ import annotations

import collections
import concurrent.futures
import copy
import dataclasses
import importlib
import os
import subprocess
import sys
import threading
from collections.abc import Sequence
from typing import Any, Callable, Optional

import mujoco
import numpy as np

from simloader import observe
from simloader import randomize as dr

_PLATFORM_LOCK = threading.Lock()
_PLATFORM: Optional[tuple[Any, str]] = None  # (GLContext class, name), chosen once
_GL_PID: Optional[int] = None  # the process that made renderers (owns GL state), if any

# Run in a short-lived child: makes a 1x1 context of platform argv[1] ("" for MUJOCO_GL's).
# The probe must not run here: a context (even freed) leaves the driver's display initialized
# in this process, with Mesa llvmpipe's rasterizer threads; a process forked from this one
# (a DataLoader worker, fork being Linux's default) inherits that state without the threads,
# and its first render waits for them forever.
_PROBE = """
import importlib, sys
name = sys.argv[1]
if name:
    cls = importlib.import_module("mujoco." + name).GLContext
else:
    from mujoco.rendering.classic import gl_context
    cls = gl_context.GLContext
context = cls(1, 1)
context.free()
"""


def _probe(name: str) -> Optional[str]:
    """None if a GL context of `name` ("" for MUJOCO_GL's) can be made, else why not; run
    in a child process so that nothing of GL is initialized in this one."""
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE, name], capture_output=True,
                              text=True, timeout=120, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return "making a 1x1 context did not finish in 120 s"
    if proc.returncode == 0:
        return None
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    return lines[-1] if lines else f"the probe exited with status {proc.returncode}"


def gl_platform() -> tuple[Any, str]:
    """The GL context class renderers use, and its name ("egl", "osmesa", or MUJOCO_GL's).

    Whether a platform works is proved in a short-lived child process; this process only
    imports the platform's module (loads its library), and makes no context: renderers make
    theirs in the process and thread that render, so the dataset can be made before a fork.

    Raises:
      RuntimeError: no GL platform works here, saying what to install.
    """
    global _PLATFORM
    with _PLATFORM_LOCK:
        if _PLATFORM is not None:
            return _PLATFORM
        asked = os.environ.get("MUJOCO_GL", "").strip().lower()
        errors = []
        if asked:
            from mujoco.rendering.classic import gl_context
            candidates = [(asked, "", lambda: gl_context.GLContext)]
        else:
            candidates = [(name, name, lambda name=name: importlib.import_module(
                f"mujoco.{name}").GLContext) for name in ("egl", "osmesa")]
        for name, module, load in candidates:
            why = _probe(module)
            if why is not None:
                errors.append(f"{name}: {why}")
                continue
            try:
                _PLATFORM = (load(), name)
                return _PLATFORM
            except Exception as e:  # noqa: BLE001 - every failure is reported below
                errors.append(f"{name}: {type(e).__name__}: {e}")
        raise RuntimeError(
            "record: simloader.Camera needs OpenGL to render on the CPU backend, and none "
            "works here (" + "; ".join(errors) + "). Install EGL (Debian/Ubuntu: libegl1 "
            "libgl1-mesa-dri libegl-mesa0; a GPU's driver provides its own) or OSMesa "
            "(libosmesa6), or set MUJOCO_GL")


def _check_not_forked_after_gl() -> None:
    """Refuses to render in a process forked from one that had already rendered: the GL
    driver's state came along without its threads, and rendering would hang."""
    if _GL_PID is not None and _GL_PID != os.getpid():
        raise RuntimeError(
            "record: simloader.Camera cannot render in a process forked after this dataset's "
            "process had already rendered (OpenGL's driver state does not survive fork; it "
            "would hang). Give the DataLoader multiprocessing_context=\"spawn\" (or "
            "\"forkserver\"), e.g. DataLoader(ds, batch_size=None, num_workers=N, "
            "multiprocessing_context=\"spawn\"), or use num_workers=0, or iterate the "
            "dataset in the main process only after the workers were started")


def check(model: mujoco.MjModel, images: Sequence[observe.CameraImage]) -> None:
    """Refuses cameras larger than the model's offscreen framebuffer, with the fix.

    Raises:
      ValueError: naming the camera, its size and the buffer's.
    """
    width, height = model.vis.global_.offwidth, model.vis.global_.offheight
    for o in images:
        if o.camera.width > width or o.camera.height > height:
            raise ValueError(
                f"record: {o.key} is {o.camera.height}x{o.camera.width} (height x width), larger "
                f"than the model's offscreen framebuffer {height}x{width}; give the model "
                f"<visual><global offwidth=\"{max(width, o.camera.width)}\" "
                f"offheight=\"{max(height, o.camera.height)}\"/></visual>, or a smaller Camera")


def _scene(renderer: mujoco.Renderer, model: mujoco.MjModel, data: mujoco.MjData,
           camera: int, option: mujoco.MjvOption) -> None:
    """`renderer.update_scene(data, camera)` for `model` (which may be another trajectory's
    model than the renderer was made with: same assets, its own colours and cameras)."""
    cam = mujoco.MjvCamera()
    cam.fixedcamid = camera
    if camera == -1:
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        mujoco.mjv_defaultFreeCamera(model, cam)
    else:
        cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
    mujoco.mjv_updateScene(model, data, option, None, cam, mujoco.mjtCatBit.mjCAT_ALL.value,
                           renderer.scene)


def _key(o: observe.CameraImage) -> tuple[int, int, bool]:
    """The renderer an image is drawn by: its size, and whether it multisamples."""
    return o.camera.height, o.camera.width, bool(o.camera.multisample)


def _quality(model: mujoco.MjModel, multisample: bool) -> mujoco.MjModel:
    """The model a renderer is made from: `model`, or without multisampling a copy with no
    offscreen samples (read when the renderer's GL context is made)."""
    if multisample:
        return model
    plain = copy.copy(model)
    plain.vis.quality.offsamples = 0
    return plain


class Renderers:
    """The renderers of one thread (one per image size and multisampling), made in it and used
    only there.

    Args:
      model: the batch's model (renderers are made from it: sizes, meshes, textures).
      images: the camera images to render.
    """

    def __init__(self, model: mujoco.MjModel, images: Sequence[observe.CameraImage]):
        global _GL_PID
        _check_not_forked_after_gl()
        _GL_PID = os.getpid()
        self.images = tuple(images)
        with _swapped_gl(gl_platform()[0]):
            self.renderers = {key: mujoco.Renderer(_quality(model, key[2]), *key[:2])
                              for key in sorted({_key(o) for o in images})}
        self.data = mujoco.MjData(model)
        self.option = mujoco.MjvOption()

    def draw(self, rows: np.ndarray, states: np.ndarray,
             model_of: Callable[[int], mujoco.MjModel], out: dict) -> None:
        """Renders trajectories `rows` of `states` ((nbatch, nframes, nintegration)
        `mjSTATE_INTEGRATION` rows) into `out` ({image key: (nbatch, nframes, *shape)})."""
        data, option = self.data, self.option
        for i in rows:
            model = model_of(int(i))
            for j in range(states.shape[1]):
                mujoco.mj_setState(model, data, states[i, j], mujoco.mjtState.mjSTATE_INTEGRATION)
                mujoco.mj_forward(model, data)
                for o in self.images:
                    r = self.renderers[_key(o)]
                    _scene(r, model, data, o.camera_id, option)
                    r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = o.camera.shadows
                    target = out[o.key][i, j]
                    if o.kind == "rgb":
                        r.render(out=target)
                    elif o.kind == "depth":
                        r.enable_depth_rendering()
                        r.render(out=target)
                        r.disable_depth_rendering()
                    else:
                        r.enable_segmentation_rendering()
                        seg = r.render()
                        r.disable_segmentation_rendering()
                        np.copyto(target, np.where(seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM,
                                                   seg[..., 0], -1))

    def close(self) -> None:
        """Frees the GL contexts (in the thread that made them: a context is current there,
        and a renderer collected in another thread fails to free it)."""
        for renderer in self.renderers.values():
            renderer.close()
        self.renderers = {}

    def __enter__(self) -> "Renderers":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class StoredFrames:
    """Stored states rendered where they are read (`StoredDataset(cameras=)` on the CPU
    engine): each thread's renderers made at its first frame, in its own process (a
    DataLoader worker makes its own), drawing exactly what `RenderPool` drew while streaming.

    Args:
      model: the store's model (renderers are made from it).
      images: the camera images to render.
    """

    def __init__(self, model: mujoco.MjModel, images: Sequence[observe.CameraImage]):
        check(model, images)
        gl_platform()  # no OpenGL here: said now, not at the first read
        self.model, self.images = model, tuple(images)
        self.token = object()  # names this reader's renderers in each thread's cache

    def __getstate__(self) -> dict:
        # to a DataLoader worker: its threads make their own renderers
        return {k: v for k, v in self.__dict__.items() if k != "token"}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state, token=object())

    def frames(self, states: np.ndarray, model_of: Callable[[int], mujoco.MjModel]) -> dict:
        """{image key: (n, nframes, *shape) tensor} of FULLPHYSICS `states` (n, nframes,
        nstate), trajectory i drawn with `model_of(i)`."""
        import torch
        rows = integration_rows(self.model, states)
        out = {o.key: np.empty((len(states), states.shape[1], *o.shape), o.dtype)
               for o in self.images}
        _thread_renderers(self.token, self.model, self.images).draw(
            range(len(states)), rows, model_of, out)
        return {k: torch.from_numpy(v) for k, v in out.items()}


# each thread's renderers of stored frames, by reader, the last `_KEPT` readers': they live
# with the thread, not with the reader, because a renderer must be freed in the thread that
# made it (its GL context is current there) and a reader may be collected in any thread
_THREAD = threading.local()
_KEPT = 4


def _thread_renderers(owner: object, model: mujoco.MjModel,
                      images: Sequence[observe.CameraImage]) -> Renderers:
    """This thread's renderers for reader `owner`, made at its first frame here; the least
    recently used reader's are freed (here, in their thread) past `_KEPT` readers."""
    if getattr(_THREAD, "pid", None) != os.getpid():  # a new thread, or a forked copy of one
        _THREAD.cache, _THREAD.pid = collections.OrderedDict(), os.getpid()
    cache = _THREAD.cache
    if owner in cache:
        cache.move_to_end(owner)
        return cache[owner]
    while len(cache) >= _KEPT:
        cache.popitem(last=False)[1].close()
    cache[owner] = Renderers(model, images)
    return cache[owner]


class RenderPool:
    """Threads that render recorded states into image buffers.

    Args:
      model: the batch's model (renderers are made from it: sizes, meshes, textures).
      images: the camera images to render.
      nthread: render threads.
    """

    def __init__(self, model: mujoco.MjModel, images: Sequence[observe.CameraImage],
                 nthread: int):
        _check_not_forked_after_gl()
        gl_platform()  # no OpenGL here: said now, not in a render thread
        self.model = model
        self.images = tuple(images)
        self.local = threading.local()
        self.pool = concurrent.futures.ThreadPoolExecutor(
            nthread, thread_name_prefix="simloader-render")
        self.nthread = nthread

    def render(self, states: np.ndarray, model_of: Callable[[int], mujoco.MjModel],
               out: dict[str, np.ndarray]) -> list[concurrent.futures.Future]:
        """Starts rendering every frame of every trajectory; returns the futures to wait on.

        Args:
          states: (nbatch, nframes, nintegration) the recorded `mjSTATE_INTEGRATION` rows.
          model_of: trajectory i's model (called in the render threads).
          out: {image key: (nbatch, nframes, *shape)} buffers to render into.
        """
        nbatch = states.shape[0]
        chunks = np.array_split(np.arange(nbatch), min(nbatch, 4 * self.nthread))
        return [self.pool.submit(self._render_rows, rows, states, model_of, out)
                for rows in chunks if len(rows)]

    def _render_rows(self, rows: np.ndarray, states: np.ndarray,
                     model_of: Callable[[int], mujoco.MjModel], out: dict) -> None:
        if not hasattr(self.local, "renderers"):  # this thread's, made at its first frame
            self.local.renderers = Renderers(self.model, self.images)
        self.local.renderers.draw(rows, states, model_of, out)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class _swapped_gl:
    """MuJoCo's Renderer takes its GL context class from `gl_context.GLContext`, fixed when
    mujoco was imported from MUJOCO_GL (glfw when unset, which needs a display): lend it the
    chosen class while a renderer is made (under a lock: renderers are made in threads)."""

    _lock = threading.Lock()

    def __init__(self, cls: Any):
        self.cls = cls

    def __enter__(self):
        from mujoco.rendering.classic import gl_context
        self._lock.acquire()
        self.module, self.before = gl_context, gl_context.GLContext
        gl_context.GLContext = self.cls

    def __exit__(self, *exc):
        self.module.GLContext = self.before
        self._lock.release()


def integration_rows(model: mujoco.MjModel, states: np.ndarray) -> np.ndarray:
    """The `mjSTATE_INTEGRATION` rows `Renderers.draw` takes, of `mjSTATE_FULLPHYSICS`
    `states` (..., nstate): the physics and every input a scene shows (mocap poses, equality
    activations) from the states, the other inputs (controls, applied forces, warmstart) as
    `mj_resetData` leaves them, which change no pixel."""
    from simloader import layout
    data = mujoco.MjData(model)
    reset = np.empty(mujoco.mj_stateSize(model, layout.INTEGRATION))
    mujoco.mj_getState(model, data, reset, layout.INTEGRATION)
    columns = layout.component_columns(model, layout.INTEGRATION, layout.FULLPHYSICS)
    rows = np.broadcast_to(reset, (*states.shape[:-1], reset.size)).copy()
    rows[..., columns] = states
    return rows


@dataclasses.dataclass(frozen=True)
class ModelPool:
    """The models a batch's trajectories ran on: one `model`, or one per batch row (`models`),
    or `variants` (picked per trajectory by `params["variant"]`), or `model` with the
    `randomization` plan's values (in `params`) written in. A `SimDataset`'s configuration
    (`of`), or what a store kept of it."""

    model: mujoco.MjModel
    models: Optional[Sequence[mujoco.MjModel]] = None
    variants: Optional[Sequence[mujoco.MjModel]] = None
    randomization: Any = None

    @classmethod
    def of(cls, config: Any) -> "ModelPool":
        return cls(config.model, config.models, config.variants, config.randomization)

    def model_of(self, params: dict[str, np.ndarray]) -> Callable[[int], mujoco.MjModel]:
        """`model_of(i)`: trajectory i's model as it ran, from the batch's `params` ({key:
        (nbatch, ...)} NumPy arrays: "variant", randomized values), for render threads:
        each thread writes the randomized values into a copy of its own."""
        if self.models is not None:
            return lambda i: self.models[i]
        if self.variants is not None:
            variant = np.asarray(params["variant"])
            return lambda i: self.variants[int(variant[i])]
        if self.randomization is None:
            return lambda i: self.model
        plan, base, local = self.randomization, self.model, threading.local()

        def model(i: int) -> mujoco.MjModel:
            if not hasattr(local, "model"):  # each render thread writes its own copy
                local.model, local.data = copy.copy(base), None
            m = local.model
            for r in plan.resolved:
                if not r.field.startswith("opt."):  # options change nothing a camera sees
                    dr._field_array(m, r.field).reshape(-1)[r.elements] = params[r.param.key][i]
            if plan.setconst:  # what MuJoCo derives from them (tracking cameras' offsets)
                local.data = local.data or mujoco.MjData(m)
                mujoco.mj_setConst(m, local.data)
            return m
        return model
