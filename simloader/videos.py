"""Videos of trajectories: `simloader.video` writes an MP4 or a GIF of some trajectories of a
batch, a store or a dataset, side by side.

Frames come from a recorded camera (`"camera/NAME/rgb"`) when the source has one, else they
are rendered from the recorded states with the CPU renderer (`simloader.render`, as the CPU
engine's cameras render: the same pixels for the same state and model). MP4s are encoded with
imageio's ffmpeg plugin (a static ffmpeg comes with the `imageio-ffmpeg` wheel: `pip install
"simloader[video]"`), GIFs with imageio's Pillow plugin.
"""

from __future__ import annotations

import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any, Optional, Union

import mujoco
import numpy as np
import torch

from simloader import layout, records, render
from simloader.batch import flat

# frames rendered per round: what is held in memory at once is this many frames of every row
CHUNK = 32
# the highest frame rate a default video plays at (in real time, taking every k-th frame)
MAX_FPS = 60
FORMATS = (".mp4", ".gif")


def video(source: Any, path: Union[str, os.PathLike], *, model: Any = None,
          rows: Union[int, Sequence[int]] = 0, camera: Union[None, str, int] = None,
          size: tuple[int, int] = (240, 320), fps: Optional[float] = None,
          lossless: bool = False, progress: bool = True) -> pathlib.Path:
    """Writes a video of trajectories `rows` of `source`, side by side (up to 4 a line).

    Args:
      source: a batch (from a `SimDataset` or a `DataLoader` over one), a
        `simloader.StoredDataset` or a store's path (rows are then stored trajectories), or a
        `SimDataset` (its first batch is simulated).
      path: the file to write, ending in ".mp4" or ".gif" (a GIF holds every frame in
        memory: keep it short).
      model: what renders the states: the `SimDataset` that made them (its randomized
        geometry, variants and model lists included, from the batch's "params"), a model
        name, an MJCF path or an `mujoco.MjModel`. Not needed for a `SimDataset` source,
        for frames of a recorded camera, or for a store that kept the one model all its
        trajectories ran with.
      rows: the trajectories to show.
      camera: a recorded camera's NAME (default: the first recorded one), or, to render from
        states, a camera of the model by name or id ("free" or -1: the free camera, the
        default).
      size: (height, width) of each rendered trajectory, in pixels.
      fps: frames per second; default: real time, from the states' time column, at most
        60 frames per second (every k-th frame is shown when the frames come faster).
      lossless: MP4 only: encode the RGB frames losslessly (libx264rgb, constant rate factor
        0), so that decoding gives the rendered pixels exactly; the default (yuv420p) plays
        everywhere and is about 10x smaller.
      progress: show a progress bar.

    Returns:
      The path written.

    Raises:
      ValueError: an unknown format, row or camera, or a source without states to render
        (naming the `record=` that keeps them).
    """
    path = pathlib.Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"path: expected a file ending in {' or '.join(FORMATS)}, got "
                         f"{str(path)!r}")
    if not isinstance(lossless, bool):
        raise ValueError(f"lossless: expected True or False, got {lossless!r}")
    if lossless and suffix != ".mp4":
        raise ValueError(f"lossless: only an MP4 can be lossless, got path {str(path)!r}")
    rows = _rows(rows)
    if isinstance(source, (str, os.PathLike)):
        from simloader.store import open_store
        source = open_store(source)
    items, nbatch, config = _items(source, rows, model)
    bad = [r for r in rows if not -nbatch <= r < nbatch]
    if bad:
        raise ValueError(f"rows: {bad} out of range for {nbatch} trajectories")
    recorded = sorted(k for k in items if k.startswith("camera/") and k.endswith("/rgb"))
    key = _recorded_key(recorded, camera)
    states = items.get("state")
    if key is None and states is None:
        raise ValueError("source: no recorded camera and no \"state\" to render from; record "
                         "the state (record=(\"state\", ...), the default) or a "
                         "simloader.Camera")
    frame_dt = None
    if states is not None and states.shape[1] > 1:
        frame_dt = float(states[0, 1, 0] - states[0, 0, 0])  # column 0 of a state is time
    stride, fps = _pace(fps, frame_dt)
    nframes = (items[key] if key is not None else states).shape[1]
    shown = np.arange(0, nframes, stride)
    if key is not None:
        frames = _recorded_frames(items[key], shown)
    else:
        # a store without model= renders with the model it kept (read only to render)
        mj_model, model_of = _renderer_models(
            _kept_model(source) if model is None else model, config, items)
        frames = _rendered_frames(mj_model, model_of, states, shown, camera, size)
    # where episodes end (`first`): the shown frame of each row that is, or follows since the
    # last shown one, a fresh start, framed in MARK
    fresh = None
    if "first" in items:
        fresh = np.logical_or.reduceat(np.asarray(items["first"], bool), shown, axis=1)
    with _Writer(path, fps, lossless) as writer:
        bar = _progress(len(shown), progress, path)
        done = 0
        for chunk in frames:  # (len(rows), k, h, w, 3) uint8
            for j in range(chunk.shape[1]):
                writer.write(_tile(chunk[:, j],
                                   None if fresh is None else fresh[:, done + j]))
            done += chunk.shape[1]
            bar.update(chunk.shape[1])
        bar.close()
    return path


def _kept_model(source: Any) -> Any:
    """The model a store kept (`provenance/models/`), where one model rendered all its
    trajectories as they ran (no model list, no variants, no randomized values); else None
    (model= is then needed)."""
    from simloader.store.reader import StoredDataset
    if not isinstance(source, StoredDataset):
        return None
    from simloader.store import pixels
    kept = source.info.get("models")
    if not isinstance(kept, dict) or kept.get("kind") != "model" or \
            any(k.startswith("params/") for k in source.layouts):
        return None
    models = pixels.kept_models(source)
    return models[0] if models else None


def _rows(rows: Any) -> list[int]:
    values = [rows] if isinstance(rows, (int, np.integer)) else rows
    try:
        out = [int(r) for r in values if not isinstance(r, bool)]
    except TypeError:
        out = None
    if (out is None or len(out) != len(values) or not out or isinstance(rows, bool)
            or any(not isinstance(r, (int, np.integer)) for r in values)):
        raise ValueError(f"rows: expected an int or a non-empty sequence of ints, got {rows!r}")
    return out


def _items(source: Any, rows: list[int], model: Any) -> tuple[dict[str, np.ndarray], int, Any]:
    """{key: (len(rows), ...) NumPy array} of the shown rows (params flattened to
    "params/KEY"), the number of trajectories the source holds, and the `SimDataset`
    configuration that made them where known."""
    from simloader.dataset import SimDataset
    from simloader.store.reader import StoredDataset

    config = model.config if isinstance(model, SimDataset) else None
    if isinstance(source, SimDataset):
        config = source.config
        source = next(iter(source))
    if isinstance(source, StoredDataset):
        n = len(source)
        picked = [r for r in rows if -n <= r < n]
        items = [flat(source[r]) for r in picked]
        out = {k: np.stack([_numpy(item[k]) for item in items]) for k in items[0]} if items else {}
        out["_row"] = np.array([source.locate(r)[1] for r in picked], dtype=np.int64)
        return out, n, config
    if isinstance(source, Mapping):
        keys = flat(source)
        if "state" not in keys and not any(k.startswith("camera/") for k in keys):
            raise ValueError(f"source: expected a batch of simloader (with \"state\" or a "
                             f"camera), got a mapping of keys {sorted(keys)[:8]}")
        n = next(iter(keys.values())).shape[0]
        picked = [r % n for r in rows if -n <= r < n]
        out = {k: _numpy(v)[picked] for k, v in keys.items()
               if getattr(v, "ndim", 0) >= 1 and v.shape[0] == n}
        out["_row"] = np.array(picked, dtype=np.int64)  # each shown row's row of its batch
        return out, n, config
    raise ValueError(f"source: expected a batch, a SimDataset, a StoredDataset or a store's "
                     f"path, got {type(source).__name__}")


def _numpy(value: Any) -> np.ndarray:
    return value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)


def _recorded_key(recorded: list[str], camera: Any) -> Optional[str]:
    """The recorded camera's key the video shows, or None to render from states."""
    if not recorded:
        return None
    if camera is None:
        return recorded[0]
    key = f"camera/{camera}/rgb"
    return key if key in recorded else None


def _pace(fps: Optional[float], frame_dt: Optional[float]) -> tuple[int, float]:
    """(stride, fps): every stride-th frame is shown, at fps frames per second."""
    if fps is not None:
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps <= 1000:
            raise ValueError(f"fps: expected a number in (0, 1000], got {fps!r}")
        return 1, float(fps)
    if frame_dt is None or not frame_dt > 0:
        return 1, 30.0
    stride = max(1, math.ceil(1.0 / (MAX_FPS * frame_dt)))
    return stride, 1.0 / (stride * frame_dt)


def _recorded_frames(images: np.ndarray, shown: np.ndarray):
    for start in range(0, len(shown), CHUNK):
        yield images[:, shown[start:start + CHUNK]]


def _renderer_models(model: Any, config: Any, items: dict):
    """(the model renderers are made from, model_of(i) for shown row i)."""
    if config is not None:
        params = {k[len("params/"):]: v for k, v in items.items() if k.startswith("params/")}
        if config.models is not None:  # a model list: entry r is batch row r's model
            rows = items["_row"]
            return config.model, lambda i: config.models[int(rows[i])]
        return config.model, render.ModelPool.of(config).model_of(params)
    if model is None:
        raise ValueError("model: rendering states needs the model that made them, and this "
                         "source keeps none to render each trajectory with (a batch, or a "
                         "store of a model list, variants or randomized values): pass model= "
                         "(the SimDataset, a model name, an MJCF path or an MjModel)")
    if isinstance(model, mujoco.MjModel):
        return model, lambda i: model
    if isinstance(model, (str, os.PathLike)):
        from simloader.models import load_model
        loaded = load_model(os.fspath(model))
        return loaded, lambda i: loaded
    raise ValueError(f"model: expected a SimDataset, a model name, an MJCF path or an "
                     f"MjModel, got {type(model).__name__}")


def _rendered_frames(model: mujoco.MjModel, model_of: Any, states: np.ndarray,
                     shown: np.ndarray, camera: Any, size: tuple[int, int]):
    nstate = mujoco.mj_stateSize(model, layout.FULLPHYSICS)
    if states.shape[-1] != nstate:
        raise ValueError(f"source: its \"state\" has {states.shape[-1]} columns, but the "
                         f"model's mjSTATE_FULLPHYSICS state has {nstate}: not this model's "
                         f"states")
    height, width = _size(size)
    image = records.camera_images(model, records.Camera(
        -1 if camera is None else camera, height=height, width=width))[0]
    render.check(model, [image])
    # rendered in this thread, with renderers made and freed here (a GL context belongs to
    # the thread that made it)
    with render.Renderers(model, [image]) as renderers:
        for start in range(0, len(shown), CHUNK):
            frames = shown[start:start + CHUNK]
            rows = render.integration_rows(model, states[:, frames])
            out = np.empty((states.shape[0], len(frames), height, width, 3), np.uint8)
            renderers.draw(range(states.shape[0]), rows, model_of, {image.key: out})
            yield out


def _size(size: Any) -> tuple[int, int]:
    if (not isinstance(size, (tuple, list)) or len(size) != 2
            or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1
                   for v in size)):
        raise ValueError(f"size: expected (height, width) in pixels, got {size!r}")
    return int(size[0]), int(size[1])


MARK = (255, 64, 0)  # the frame around a fresh start (an episode's first frame)


def _tile(frames: np.ndarray, marked: Optional[np.ndarray] = None) -> np.ndarray:
    """One picture of (n, h, w, 3) frames, 4 a line, padded black to even sides (H.264's
    4:2:0 colour needs them); the frames `marked` ((n,) bool) framed in `MARK` (in the
    picture: the frames themselves are left as they are)."""
    n, h, w, _ = frames.shape
    cols = min(n, 4)
    lines = -(-n // cols)
    out = np.zeros((lines * h + (lines * h) % 2, cols * w + (cols * w) % 2, 3), np.uint8)
    border = max(1, min(h, w) // 24)
    for i in range(n):
        r, c = divmod(i, cols)
        tile = out[r * h:(r + 1) * h, c * w:(c + 1) * w]
        tile[...] = frames[i]
        if marked is not None and marked[i]:
            for edge in (tile[:border], tile[-border:], tile[:, :border], tile[:, -border:]):
                edge[...] = MARK
    return out


def _progress(total: int, show: bool, path: pathlib.Path):
    from tqdm.auto import tqdm
    return tqdm(total=total, disable=not show or None, desc=f"simloader video {path.name}",
                unit="frame", leave=False)


class _Writer:
    """Frames to an MP4 (streamed to ffmpeg) or a GIF (kept, then written at once)."""

    def __init__(self, path: pathlib.Path, fps: float, lossless: bool):
        self.path, self.fps, self.lossless = path, fps, lossless
        self.gif = path.suffix.lower() == ".gif"
        self.frames: list[np.ndarray] = []
        self.encoder = None

    def __enter__(self) -> "_Writer":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.gif:
            try:
                import imageio_ffmpeg
            except ImportError as e:
                raise ImportError("simloader.video: writing an MP4 needs imageio-ffmpeg: pip "
                                  "install \"simloader[video]\"") from e
            self.imageio_ffmpeg = imageio_ffmpeg
        return self

    def write(self, frame: np.ndarray) -> None:
        if self.gif:
            self.frames.append(frame)
            return
        if self.encoder is None:
            size = (frame.shape[1], frame.shape[0])
            options = (dict(codec="libx264rgb", pix_fmt_out="rgb24", quality=None,
                            output_params=["-crf", "0", "-preset", "veryfast"])
                       if self.lossless else dict(codec="libx264", pix_fmt_out="yuv420p"))
            self.encoder = self.imageio_ffmpeg.write_frames(
                str(self.path), size, fps=self.fps, macro_block_size=1,
                ffmpeg_log_level="error", **options)
            self.encoder.send(None)  # starts ffmpeg
        self.encoder.send(np.ascontiguousarray(frame))

    def __exit__(self, kind, value, traceback) -> None:
        if self.encoder is not None:
            self.encoder.close()
        if self.gif and kind is None:
            try:
                import imageio.v3 as iio
            except ImportError as e:
                raise ImportError("simloader.video: writing a GIF needs imageio: pip install "
                                  "\"simloader[video]\"") from e
            iio.imwrite(self.path, np.stack(self.frames), extension=".gif",
                        duration=1000.0 / self.fps, loop=0)
