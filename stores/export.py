"""Exports to the formats other tools read: ``exr``, ``oidn`` and ``layerdenoise`` (``noisebase``, which needs
the renderer, is added by :mod:`pipeline.export`: ``python -m pipeline export`` has all four).

``main(argv)`` is ``python -m pipeline export STORE --frames ... --format F --out DIR``. Only frames
``validate`` passes are exported (:mod:`stores.fitness`, the check every command applies: complete,
finite, non-negative references, no all-zero reference under a non-zero input, no NaN the renderer
replaced); an unfit frame is an error naming it, or with ``--skip-bad-frames`` left out and named.
Files are written into a temporary folder inside ``DIR`` and moved into place once every frame is
written, so an export that stops (a damaged store, a full disk, Ctrl-C) leaves no half of itself.

* ``exr``: per frame a folder ``frame_NNNNNN/`` with OpenEXR files (float32, ZIP):
  ``input_mean.exr`` (mean of the per-sample radiance), ``layer_NNNNspp.exr`` (each sample layer),
  ``reference.exr``, ``reference_stderr.exr`` (RGB), ``albedo.exr`` (RGB), ``normal.exr`` (RGB = world xyz),
  ``depth.exr`` (``Z``, OpenEXR's depth channel name), ``motion.exr`` (``motion_to_prev.x``,
  ``motion_to_prev.y``: the screen-space offset to the pixel's position in the previous frame,
  ``p_prev - p_cur`` in pixels, x right, y down), and 8-bit PNG previews
  (``*.png``, :func:`core.images.to_srgb8`) of input_mean, layers and reference through the
  training tone map (``log(1 + x)`` then the sRGB curve, the layer paper's eq. 7, clipped to [0, 1]),
  of albedo through the sRGB curve, and of normal as ``n * 0.5 + 0.5``.
* ``oidn``: the naming read by Intel Open Image Denoise's training toolkit (``training/dataset.py``:
  images are grouped by the name before the last ``_``; a ``NNNNspp`` suffix is an input, ``ref`` the
  target; features are ``.hdr.exr``, ``.alb.exr``, ``.nrm.exr`` with channels R, G, B). One input set per
  sample layer: ``fNNNNNN_0001spp.hdr.exr`` ... ``fNNNNNN_0032spp.hdr.exr`` with the frame's per-pixel
  ``.alb.exr``/``.nrm.exr`` guides, and ``fNNNNNN_ref.hdr.exr`` (+ ``.alb``/``.nrm``). (The per-sample
  inputs are not exported here: their mean would collide with the 8-spp layer's name.)
* ``layerdenoise``: HDF5 as read by NVlabs/layerdenoise ``datasets.py``: ``NAME_input.h5`` holding
  ``[frames, samples, channels, H, W]`` float16 datasets ``color`` (3), ``normals_depth`` (4: view-space
  normal, depth divided by the largest sample depth of the frame's clip), ``albedo`` (3), ``specular`` (4: specular
  colour + roughness), ``uvt`` (3: lens u, v + time), ``motionvecs`` (3: NDC motion x, y + signed CoC in
  pixels), and ``NAME_ref.h5`` with ``color [frames, 3, H, W]`` (the loader derives the reference file
  name by replacing the last ``_...`` with ``_ref.h5``). View space is layerdenoise's: +x right, +y up,
  +z towards the viewer (its ``augment_rot90`` maps ``(nx, ny) -> (-ny, nx)``, its flips negate nx or
  ny), i.e. Mitsuba's camera frame (``R^T n_world`` with ``R`` of ``camera_to_world``: +x left, +y up,
  +z forward) turned 180 degrees about y: ``(-x, y, -z)``. Depth is normalised per clip (the same
  surface keeps its value from frame to frame): divided by the largest per-sample depth over every
  complete frame of the clip in the store, whichever frames are exported; the scale of each exported
  frame is in the input file's attribute ``depth_scale``. NDC motion is ``(2 mx / W, -2 my / H)`` (y up).
  float16 saturates at 65504: radiance above it is clamped (the loader clips at 65535 anyway).
"""
from __future__ import annotations

import argparse
import os

import numpy as np

from stores.contract import FEATURE_GROUPS, FRAME_ARRAYS
from stores.errors import ExportError, StoreError
from core.images import read_exr_channels, write_exr, write_png
from stores.reader import Store, open_store
from stores.validate import parse_frames

FORMATS = ("exr", "oidn", "layerdenoise")       # the formats of the store alone (more: :func:`writers`)


# ``{"RGB": ...}``-style reading, for callers of this module's former reader
read_exr = read_exr_channels


DEPTH_CHANNEL = ["Z"]                                    # OpenEXR's name for depth
MOTION_CHANNELS = ["motion_to_prev.x", "motion_to_prev.y"]   # p_prev - p_cur, pixels, x right, y down


def export_exr(store: Store, frames: list[int], out: str) -> list[str]:
    """Write the ``exr`` format (module docstring). Returns the files written."""
    written = []
    for i in frames:
        fr = store.read_frame(i, [k for k in FRAME_ARRAYS if k not in ("camera_to_world", "world_to_clip")])
        d = os.path.join(out, f"frame_{i:06d}")
        os.makedirs(d, exist_ok=True)
        imgs = {"input_mean": fr["radiance"].mean(axis=2), "reference": fr["reference"],
                "reference_stderr": fr["reference_stderr"], "albedo": fr["guides_albedo"],
                "normal": fr["guides_normal"]}
        for n, s in enumerate(store.layout.layer_spp):
            imgs[f"layer_{s:04d}spp"] = fr["layers"][n]
        for name, rgb in imgs.items():
            write_exr(os.path.join(d, f"{name}.exr"), rgb)
            written.append(os.path.join(d, f"{name}.exr"))
            if name == "reference_stderr":
                continue
            if name == "normal":
                write_png(os.path.join(d, f"{name}.png"), rgb * 0.5 + 0.5, mode="linear")
            else:
                write_png(os.path.join(d, f"{name}.png"), rgb, mode="clamp" if name == "albedo" else "log")
            written.append(os.path.join(d, f"{name}.png"))
        write_exr(os.path.join(d, "depth.exr"), fr["guides_depth"][..., :1], channels=DEPTH_CHANNEL)
        write_exr(os.path.join(d, "motion.exr"), fr["guides_motion"][..., :2], channels=MOTION_CHANNELS)
        written += [os.path.join(d, "depth.exr"), os.path.join(d, "motion.exr")]
    return written


def export_oidn(store: Store, frames: list[int], out: str) -> list[str]:
    """Write the ``oidn`` format (module docstring). Returns the files written."""
    os.makedirs(out, exist_ok=True)
    written = []
    for i in frames:
        fr = store.read_frame(i, ["layers", "reference", "guides_albedo", "guides_normal"])
        base = os.path.join(out, f"f{i:06d}")
        alb, nrm = np.clip(fr["guides_albedo"], 0, 1), fr["guides_normal"]
        sets = [(f"{s:04d}spp", fr["layers"][n]) for n, s in enumerate(store.layout.layer_spp)]
        sets.append(("ref", fr["reference"]))
        for suffix, color in sets:
            for feat, img in (("hdr", color), ("alb", alb), ("nrm", nrm)):
                path = f"{base}_{suffix}.{feat}.exr"
                write_exr(path, img)
                written.append(path)
    return written


# Mitsuba's camera frame (+x left, +y up, +z forward) -> layerdenoise's view space (+x right, +y up,
# +z towards the viewer): a 180-degree turn about y, so still a rotation (right-handed to right-handed).
MITSUBA_TO_VIEW = np.diag([-1.0, 1.0, -1.0])


def _view_normals(n_world: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
    """``n_world (..., 3)`` -> view-space normals (+x right, +y up, +z towards the viewer):
    ``MITSUBA_TO_VIEW @ R^T @ n`` with ``R`` of ``camera_to_world``."""
    R = np.asarray(cam_to_world, np.float64)[:3, :3]
    M = MITSUBA_TO_VIEW @ R.T
    return (n_world.astype(np.float64) @ M.T).astype(np.float32)   # row vectors: n @ M^T == (M n^T)^T


def clip_depth_scales(store: Store, frames: list[int]) -> dict[int, float]:
    """frame -> the largest per-sample depth over every complete frame of its clip (1.0 if none is
    positive), the per-clip depth normalisation of the ``layerdenoise`` export."""
    from stores.contract import FEATURE_NAMES
    d = FEATURE_NAMES.index("depth")
    clip_of = store.meta_column("clip_id")
    members = store.clips(None)
    scale_of_clip: dict[int, float] = {}
    out = {}
    for i in frames:
        c = int(clip_of[i])
        if c not in scale_of_clip:
            top = 0.0
            for j in members.get(c, [i]):
                depth = store.read_array("inputs/features", j)[:, d].astype(np.float32)   # (S, h, w)
                fin = depth[np.isfinite(depth)]
                if fin.size:
                    top = max(top, float(fin.max()))
            scale_of_clip[c] = top if top > 0 else 1.0
        out[i] = scale_of_clip[c]
    return out


def export_layerdenoise(store: Store, frames: list[int], out: str, name: str = "dataset") -> list[str]:
    """Write ``NAME_input.h5`` and ``NAME_ref.h5`` (module docstring). Returns the two paths."""
    import h5py
    os.makedirs(out, exist_ok=True)
    lay = store.layout
    F, S, H, W = len(frames), lay.spp, lay.height, lay.width
    f16 = np.float16
    inp, ref = os.path.join(out, f"{name}_input.h5"), os.path.join(out, f"{name}_ref.h5")
    shapes = {"color": 3, "normals_depth": 4, "albedo": 3, "specular": 4, "uvt": 3, "motionvecs": 3}
    g = FEATURE_GROUPS
    scales = clip_depth_scales(store, frames)
    with h5py.File(inp, "w") as hi, h5py.File(ref, "w") as hr:
        ds = {k: hi.create_dataset(k, (F, S, c, H, W), dtype=f16, chunks=(1, S, c, H, W))
              for k, c in shapes.items()}
        dref = hr.create_dataset("color", (F, 3, H, W), dtype=f16, chunks=(1, 3, H, W))
        for j, i in enumerate(frames):
            fr = store.read_frame(i, ["radiance", "features", "reference", "camera_to_world"])
            rad, feat = fr["radiance"], fr["features"]                  # (H, W, S, 3), (H, W, S, 17)
            to_sc = lambda a: np.moveaxis(a, (2, 3), (0, 1))           # noqa: E731  (H,W,S,C)->(S,C,H,W)
            depth = feat[..., g["depth"]]
            dmax = scales[i]
            nview = _view_normals(feat[..., g["normal"]], fr["camera_to_world"])
            motion = feat[..., g["motion"]] * np.array([2.0 / W, -2.0 / H], np.float32)
            blocks = {
                "color": np.minimum(rad, 65504.0),
                "normals_depth": np.concatenate([nview, depth / dmax], axis=-1),
                "albedo": feat[..., g["albedo"]],
                "specular": np.concatenate([feat[..., g["specular"]], feat[..., g["roughness"]]], axis=-1),
                "uvt": np.concatenate([feat[..., g["lens"]], feat[..., g["time"]]], axis=-1),
                "motionvecs": np.concatenate([motion, feat[..., g["coc"]]], axis=-1),
            }
            for k, a in blocks.items():
                ds[k][j] = to_sc(a).astype(f16)
            dref[j] = np.minimum(fr["reference"], 65504.0).transpose(2, 0, 1).astype(f16)
        hi.attrs["frames"] = np.asarray(frames, np.int64)
        hi.attrs["depth_scale"] = np.asarray([scales[i] for i in frames], np.float64)
        hi.attrs["normals"] = "view space: +x right, +y up, +z towards the viewer"
        hi.attrs["source"] = os.fspath(store.path)
    return [inp, ref]


def export(store_path, frames: str | list[int] | None, fmt: str, out: str, name: str = "dataset", *,
           skip_bad_frames: bool = False) -> list[str]:
    """Export ``frames`` (``'all'``, ``'0,2,5-7'`` or a list) of the store in format ``fmt`` into ``out``.
    Frames ``validate`` flags are refused (``UnfitFrameError`` naming them), or left out with a warning
    when ``skip_bad_frames``. Everything is written into a temporary folder in ``out`` first and moved
    into place at the end (:func:`_into_place`): a failed export leaves ``out`` as it was."""
    from stores.fitness import screen_items
    write = _writer(fmt)
    store = open_store(store_path)
    idx = frames if isinstance(frames, list) else parse_frames(frames, store.num_frames)
    if not idx:
        raise ExportError("no frames to export")
    idx, left_out = screen_items(store, idx, skip=skip_bad_frames, what=f"the export of {store_path!s}",
                                 progress=True)
    made = _missing_parents(out)
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        raise ExportError(f"cannot make the output folder {out}: {e.strerror or e}") from e
    import shutil
    import tempfile
    tmp = tempfile.mkdtemp(prefix=".export-", dir=out)
    done = False
    try:
        files = write(store, idx, tmp, name, left_out)
        done = True
        return _into_place(tmp, out, files)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not done:                    # a refused export leaves no folder it made behind
            for d in made:
                try:
                    os.rmdir(d)
                except OSError:
                    break


def _missing_parents(out: str) -> list[str]:
    """The folders ``os.makedirs(out)`` would make, deepest first."""
    made, d = [], os.path.abspath(out)
    while not os.path.exists(d):
        made.append(d)
        d = os.path.dirname(d)
    return made


# format -> writer(store, frames, out, name, left_out) -> files: the store's own formats (``left_out``: the
# frames --skip-bad-frames left out, frame -> problems; a format whose files hold runs of frames, Noisebase's
# sequences, splits its runs there). Formats that need more than the store are plug-ins (:data:`PLUGINS`,
# :func:`writers`): ``noisebase``, which re-traces the samples with the renderer, is ``pipeline.noisebase``'s.
WRITERS = {"exr": lambda st, fr, out, name, left_out: export_exr(st, fr, out),
           "oidn": lambda st, fr, out, name, left_out: export_oidn(st, fr, out),
           "layerdenoise": lambda st, fr, out, name, left_out: export_layerdenoise(st, fr, out, name)}
PLUGINS = "denoise_datagen.export_formats"      # the entry-point group (pyproject.toml) of the other formats


def _plugins() -> dict:
    """name -> entry point of every installed export format plug-in (nothing is imported here)."""
    from importlib.metadata import entry_points
    return {ep.name: ep for ep in entry_points(group=PLUGINS) if ep.name not in WRITERS}


def writers() -> dict:
    """Every export format, the store's own and the installed plug-ins': name -> writer, or an entry
    point loaded when the format is used. Both ``python -m stores export`` and ``python -m pipeline
    export`` offer these."""
    return {**WRITERS, **_plugins()}


def _writer(fmt: str):
    found = writers()
    if fmt not in found:
        raise ExportError(f"unknown export format {fmt!r}; choose one of {tuple(found)} (a plug-in format comes "
                          "with the installed package: `make setup` or `pip install -e .` brings a missing one)")
    w = found[fmt]
    if callable(w):
        return w
    try:
        return w.load()
    except ImportError as e:
        raise ExportError(f"the export format {fmt!r} ({w.value}) cannot be loaded: {e}") from e


def _into_place(tmp: str, out: str, files: list[str]) -> list[str]:
    """Move every entry of ``tmp`` into ``out`` (an entry of the same name there, an earlier export of
    the same frame, is replaced); returns ``files`` as paths in ``out``."""
    import shutil
    for entry in sorted(os.listdir(tmp)):
        dst = os.path.join(out, entry)
        if os.path.isdir(dst) and not os.path.islink(dst):
            shutil.rmtree(dst)
        os.replace(os.path.join(tmp, entry), dst)
    return [os.path.join(out, os.path.relpath(f, tmp)) for f in files]


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The ``export`` sub-command's arguments (shared by ``python -m pipeline`` and ``python -m stores``)."""
    ap.add_argument("store", help="path of the Zarr store")
    ap.add_argument("--frames", default="all", help="all (default), 3, 0,2,5-7")
    ap.add_argument("--format", required=True, choices=tuple(writers()))
    ap.add_argument("--out", required=True, help="output folder")
    ap.add_argument("--name", default="dataset", help="file name stem for layerdenoise (NAME_input.h5)")
    ap.add_argument("--skip-bad-frames", action="store_true",
                    help="leave out frames validate flags (NaN/Inf, negative or all-zero references, NaN the "
                         "renderer replaced), naming them; default: refuse them")



def run(args) -> int:
    """Export and print a one-line summary; raises StoreError (ExportError, ...) on failure."""
    try:
        files = export(args.store, args.frames, args.format, args.out, args.name,
                       skip_bad_frames=getattr(args, "skip_bad_frames", False))
    except ValueError as e:
        if isinstance(e, StoreError):
            raise
        raise ExportError(str(e)) from e
    print(f"wrote {len(files)} files to {args.out}")
    return 0
