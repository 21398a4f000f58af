"""``python -m training denoise``: apply a trained checkpoint to your own render, like OIDN's ``oidnDenoise``.

    python -m training denoise --checkpoint CKPT --input noisy.exr [--albedo a.exr --normal n.exr
                               --depth d.exr] --out out.exr
    python -m training denoise --checkpoint CKPT --input frame.npz --out out.exr     # render-frame's .npz
    python -m training denoise --checkpoint CKPT --store S.zarr --frame I --out out.exr

What a model reads decides the input it accepts (``training.inputs``):

* per-pixel models (kind ``pixels``: nbg, wskpn) take EXR images: the noisy radiance and the guides the
  model was trained with (albedo, normal, depth), each read by channel name (:data:`CHANNELS`): separate
  files, or one multichannel file for all (Mitsuba's ``aov`` integrator's ``albedo.R``, ``sh_normal.X``,
  ``depth.T`` beside R, G, B). A missing guide, or a file without the channels a guide needs, is an error
  naming them: a denoiser fed a made-up guide gives a plausible but wrong image.
* per-sample models (kind ``samples``/``clips``: the layer family) need the samples of every pixel: the
  ``.npz`` of ``python -m pipeline render-frame`` (``radiance`` HWS3, ``features`` HWS17) or a store frame.
* samplers (kind ``sampled-layers``: temporal) compose their input from sample layers: an ``.npz`` or a
  store frame. A recurrent model denoises a store frame after running the frames of its clip before it,
  carrying its state, as in evaluation (an ``.npz`` is a clip's first frame).
* ``--checkpoint oidn`` runs Intel Open Image Denoise on the same inputs (guides optional).

An EXR's data window is kept: the radiance's pixels are denoised where its data window puts them, each
guide (of the same display window, its data window covering the radiance's) is taken at those pixels,
and the output is written with the radiance's data and display windows. Guides of another display
window, or whose pixels do not cover the radiance's, are refused naming both windows.

Any model gets an ``.npz`` or a store frame; each is turned into the model's input as in training (the
mean of the first N samples and of their features for a per-pixel model, N the checkpoint's spp unless
``--spp``). Images that differ in size, and NaN or Inf in the radiance or a guide, are refused with the
count and the first pixel (clean them, or re-render: the store's NaN/Inf rule does this for renders).

Large images are denoised in tiles (``--tile``, or automatically above :data:`AUTO_TILE_PIXELS`): each
tile is run with a margin of :data:`TILE_MARGIN` pixels of context on every side (its origin aligned to
:data:`TILE_ALIGN`, so the networks' downsampling grid is the whole image's) and only its centre is kept.
Memory then follows the tile, not the image; the result differs from a whole-image pass only where the
model looks further than the margin (the bilateral grid's cells, the deepest U-net levels).
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from .errors import ConfigError, DataError

AUTO_TILE_PIXELS = 1024 * 1024      # larger images are tiled automatically (peak memory of a pass grows with it)
AUTO_TILE = 512
TILE_MARGIN = 32
TILE_ALIGN = 16                     # the deepest downsampling of the registered U-nets (4 levels of 2x)
GUIDES = ("albedo", "normal", "depth")


# --------------------------------------------------------------------------------------------
# Loading


def load_method(checkpoint: str, device: str = "cpu", compile: bool = False):
    """``(model in inference form, spec, train spp, name)``, or ``(None, None, None, "oidn")``.
    ``compile``: through ``torch.compile`` (:func:`training.accel.compile_model`)."""
    if checkpoint == "oidn":
        return None, None, None, "oidn"
    from . import checkpoint as ckpt
    path = Path(checkpoint)
    if not path.is_file():
        raise ConfigError(f"--checkpoint {checkpoint}: no such file (a checkpoint.pt written by "
                          "`python -m training train`, or 'oidn')")
    ck = ckpt.load(path, map_location=device)
    model = ckpt.build_model(ck, device)
    spec = model.input_spec()
    spp = int(ck["train_config"].get("spp") or spec.default_spp)
    fast = model.for_inference()
    if compile:
        from .accel import compile_model
        fast = compile_model(fast)
    return fast, spec, spp, ck["model"]


def _finite(name: str, a: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(a)
    if bad.any():
        where = np.argwhere(bad)[0]
        raise DataError(f"{name} has {int(bad.any(axis=-1).sum() if a.ndim == 3 else bad.sum())} pixel(s) "
                        f"with NaN or Inf (the first at y={where[0]}, x={where[1]}); replace them (e.g. by 0) "
                        "before denoising")
    return a


def _layer(layers, suffixes) -> list[tuple[str, ...]]:
    return [tuple(f"{lay}.{c}" if lay else c for c in suf) for lay in layers for suf in suffixes]


# What each image is read from, by channel name, in order of preference: the layers renderers write
# (Mitsuba's `aov` integrator: albedo.R, sh_normal.X, depth.T beside the image's R, G, B; OpenEXR's N.X, Z),
# then a plain image's own channels, which only a file without layers may give to a guide (a multichannel
# file's R, G, B are its radiance, never its albedo). Channels are taken by name in R, G, B / X, Y, Z order,
# never in the file's (alphabetical) order.
CHANNELS = {
    "input": {"layered": [], "plain": [("R", "G", "B")]},
    "albedo": {"layered": _layer(["albedo"], ["RGB", "XYZ"]), "plain": [("R", "G", "B")]},
    "normal": {"layered": _layer(["sh_normal", "normal", "N"], ["XYZ", "RGB"]),
               "plain": [("X", "Y", "Z"), ("R", "G", "B")]},
    "depth": {"layered": _layer(["depth"], ["T", "Z", "Y"]), "plain": [("Z",), ("Y",), ("depth",)]},
}


def image_channels(names: list[str], role: str) -> tuple[str, ...] | None:
    """The channels of a file with channels ``names`` that hold ``role`` (``input``, ``albedo``,
    ``normal``, ``depth``; :data:`CHANNELS`), in the order the image needs, or None."""
    have, rule = set(names), CHANNELS[role]
    unlayered = not any("." in n for n in names)
    for cand in rule["layered"] + (rule["plain"] if unlayered or role == "input" else []):
        if have.issuperset(cand):
            return cand
    return None


def _accepted(role: str) -> str:
    rule = CHANNELS[role]
    text = [",".join(c) for c in rule["layered"][:4]] + [",".join(c) for c in rule["plain"]]
    return " or ".join(text) + ("" if role == "input" else " (the plain channels only in a file without layers)")


def _read_image(path: str, name: str) -> np.ndarray:
    """The image ``--NAME PATH`` holds for ``name``, its channels chosen by name (:data:`CHANNELS`)."""
    from core.images import exr_channel_names, read_exr_named
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--{name} {path}: no such file")
    try:
        names = exr_channel_names(p)
    except Exception as e:  # noqa: BLE001 - OpenEXR raises plain exceptions for non-EXR files
        raise DataError(f"--{name} {path} is not a readable OpenEXR image: {e}") from e
    chosen = image_channels(names, name)
    if chosen is None:
        raise DataError(f"--{name} {path} has channels {','.join(names)}; the {name} is read from channels "
                        f"{_accepted(name)}")
    return _finite(f"--{name} {path}", read_exr_named(p, chosen))


def _chw(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(a, np.float32), -1, 0)))


def items_from_exr(spec, a) -> list[dict]:
    """One item (channel-first tensors) from ``--input`` and the guide EXRs, for a model whose input kind
    reads per-pixel images (or OIDN: ``spec`` None, guides optional)."""
    rad = _read_image(a.input, "input")
    kind = _kind(spec)
    if not kind.reads_images:
        raise ConfigError(f"this model reads {kind.holds} (input kind {kind.name!r}), which an EXR image does not "
                          "hold: give the .npz of `python -m pipeline render-frame` as --input, or --store S --frame I")
    if spec is not None and spec.frames > 1:
        raise ConfigError(f"this model accumulates {spec.frames} frames of a clip; denoise a store frame "
                          "(--store S --frame I) so that it gets the frames before it")
    need = GUIDES if spec is not None else ("albedo", "normal")
    missing = [g for g in need if getattr(a, g) is None] if spec is not None else []
    if missing:
        raise ConfigError(f"this model was trained with the albedo, normal and depth guides; "
                          f"{', '.join('--' + g for g in missing)} missing (write them from your renderer's AOVs; "
                          "a made-up guide gives a plausible but wrong image)")
    images = {"radiance": _chw(rad)}
    for g in need:
        path = getattr(a, g)
        if path is None:
            continue
        images[g] = _chw(_at_input(_read_image(path, g), path, g, a.input))
    return [kind.item_from_images(images)]


def _size(w) -> str:
    return f"{w[2] - w[0] + 1}x{w[3] - w[1] + 1}"


def _at_input(img: np.ndarray, path: str, name: str, input_path: str) -> np.ndarray:
    """Guide ``img`` (the pixels of its data window) at the pixels of ``--input``'s data window. Both files
    must share one display window (one render's), and the guide's data window must cover the input's;
    otherwise DataError naming both windows."""
    from core.images import exr_windows, window_text as wt
    (gx0, gy0, gx1, gy1), gdisp = exr_windows(path)
    (x0, y0, x1, y1), disp = exr_windows(input_path)
    if gdisp != disp:
        raise DataError(f"--{name} {path} has display window {wt(gdisp)} ({_size(gdisp)}); --input {input_path} has "
                        f"{wt(disp)} ({_size(disp)}): a guide must come from the same render as the input")
    if not (gx0 <= x0 and gy0 <= y0 and x1 <= gx1 and y1 <= gy1):
        raise DataError(f"--{name} {path} holds the pixels {wt((gx0, gy0, gx1, gy1))} of its display window "
                        f"{wt(disp)}, which do not cover those of --input {input_path}, {wt((x0, y0, x1, y1))} (its "
                        "data window): write the guide over the whole image or over the input's window")
    return img[y0 - gy0:y1 - gy0 + 1, x0 - gx0:x1 - gx0 + 1]


def _kind(spec):
    """The input kind of ``spec`` (None, OIDN: the per-pixel kind the baselines read)."""
    from .inputs import KINDS
    return KINDS["pixels"] if spec is None else spec.input_kind


def items_from_npz(spec, path: str, spp: int) -> list[dict]:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--input {path}: no such file")
    try:
        with np.load(p, allow_pickle=False) as z:
            item = _kind(spec).item_from_render({k: z[k] for k in z.files}, spp)
    except (ValueError, OSError) as e:
        raise DataError(f"--input {path} is not a readable .npz: {e}") from e
    for k, v in item.items():              # render-frame writes finite arrays (the NaN/Inf rule); an edited file may not
        bad = int((~torch.isfinite(v)).sum()) if v.is_floating_point() else 0
        if bad:
            raise DataError(f"{k} of {path} has {bad} NaN or Inf value(s); replace them (e.g. by 0) before denoising")
    return [item]


def items_from_store(spec, store: str, frame: int, spp: int, stepwise: bool) -> list[dict]:
    """The model's item for store frame ``frame`` (preceded by the frames of its clip before it, for a
    recurrent model), built as in evaluation."""
    from .data import model_dataset, open_store
    from .evaluate import baseline_spec
    st = open_store(store)
    n = st.layout.num_frames
    if not isinstance(frame, int) or not 0 <= frame < n:
        raise ConfigError(f"--frame {frame}: the store has frames 0..{n - 1}")
    if frame not in st.frames_in_split(None):
        raise DataError(f"frame {frame} of {st.path} is not complete (see python -m pipeline validate)")
    split = st.split_of_frame(frame)
    if spec is None:
        spec = baseline_spec(spp)
    if stepwise or spec.frames == 1:
        spec = replace(spec, frames=1)                  # single frames, the model's features kept
    ds = model_dataset(spec, st, split, spp, None, augment=False, seed=0, full_windows=False)
    ends = [int(w[-1]) for w in ds.windows]
    if frame not in ends:
        raise DataError(f"frame {frame} of {st.path} is not usable ({split} split)")
    pos = ends.index(frame)
    if not stepwise:
        return [ds[pos]]
    clip, in_clip = st.meta_column("clip_id"), st.meta_column("frame")
    first = pos
    while (first > 0 and clip[ends[first - 1]] == clip[frame]
           and int(in_clip[ends[first - 1]]) + 1 == int(in_clip[ends[first]])):
        first -= 1
    return [ds[p] for p in range(first, pos + 1)]


# --------------------------------------------------------------------------------------------
# Running


def _check_sizes(items: list[dict]) -> tuple[int, int]:
    sizes = {tuple(v.shape[-2:]) for it in items for k, v in it.items() if torch.is_tensor(v) and v.dim() >= 3}
    if len(sizes) != 1:
        raise DataError(f"the inputs differ in size: {sorted(sizes)}")
    return sizes.pop()


def _run_oidn(item: dict) -> np.ndarray:
    from .oidn import oidn_denoise
    im = {k: v.permute(1, 2, 0).numpy() for k, v in _kind(None).noisy_image(item, 0).items()}
    return oidn_denoise(im["radiance"], im.get("albedo"), im.get("normal"))


def run_sequence(model, items: list[dict], device: str = "cpu", precision: str = "fp32") -> np.ndarray:
    """The model's output (HW3 float32) for the last item; a recurrent model steps through all of them.
    ``precision``: the forward pass's autocast (bf16, fp16 or fp32)."""
    if model is None:
        return _run_oidn(items[-1])
    from .accel import autocast
    kind, state = model.input_spec().input_kind, None
    with torch.no_grad(), autocast(torch.device(device), precision):
        for item in items:
            batch = {k: v.unsqueeze(0).to(device) for k, v in item.items() if torch.is_tensor(v)}
            out, state, _ = kind.stream(model, batch, state)
    out = out[0]
    if out.dim() == 4:                       # a window's outputs: the last frame's
        out = out[-1]
    return out.float().permute(1, 2, 0).cpu().numpy()


def tiles(H: int, W: int, tile: int, margin: int = TILE_MARGIN, align: int = TILE_ALIGN):
    """``(read window (y0, y1, x0, x1), keep window in image coordinates)`` of each tile: cores of
    ``tile`` px on a grid, each read with ``margin`` px of context, the read origin aligned to ``align``."""
    for cy in range(0, H, tile):
        for cx in range(0, W, tile):
            ky1, kx1 = min(cy + tile, H), min(cx + tile, W)
            y0, x0 = max(0, (cy - margin) // align * align), max(0, (cx - margin) // align * align)
            y1, x1 = min(H, ky1 + margin), min(W, kx1 + margin)
            yield (y0, y1, x0, x1), (cy, ky1, cx, kx1)


def _crop(items: list[dict], y0, y1, x0, x1) -> list[dict]:
    return [{k: (v[..., y0:y1, x0:x1] if torch.is_tensor(v) and v.dim() >= 3 else v) for k, v in it.items()}
            for it in items]


def denoise(model, items: list[dict], tile: int = 0, device: str = "cpu", progress: bool = False,
            precision: str = "fp32") -> np.ndarray:
    """Denoise the last of ``items`` (see :func:`run_sequence`), in tiles of ``tile`` px (0: automatic,
    the whole image up to :data:`AUTO_TILE_PIXELS`; < 0: never)."""
    H, W = _check_sizes(items)
    if tile == 0:
        tile = AUTO_TILE if H * W > AUTO_TILE_PIXELS else -1
    if tile < 0 or (tile >= H and tile >= W):
        return run_sequence(model, items, device, precision)
    out = np.zeros((H, W, 3), np.float32)
    grid = list(tiles(H, W, tile))
    for i, ((y0, y1, x0, x1), (ky0, ky1, kx0, kx1)) in enumerate(grid):
        part = run_sequence(model, _crop(items, y0, y1, x0, x1), device, precision)
        out[ky0:ky1, kx0:kx1] = part[ky0 - y0:ky1 - y0, kx0 - x0:kx1 - x0]
        if progress:
            print(f"\rtile {i + 1}/{len(grid)}", end="", file=sys.stderr, flush=True)
    if progress:
        print(file=sys.stderr)
    return out


ANY_SPP_KINDS = ("samples", "clips")     # per-sample models: each sample is its own input, any count of them


def spp_note(spec, name: str, train_spp, spp, *, exr: bool) -> str | None:
    """The one line ``denoise`` prints about samples per pixel, or None: a per-pixel (or sampling) model fed
    another count than it was trained at (``--spp`` states an EXR's; a store or .npz frame is composed at
    ``--spp``) is warned, saying what it expects; an EXR without ``--spp`` gets a note that its count is
    unknown. Per-sample models (:data:`ANY_SPP_KINDS`) take any count; OIDN (``spec`` None) too."""
    if spec is None or spec.kind in ANY_SPP_KINDS or train_spp is None:
        return None
    if spp is None:
        if not exr:
            return None
        return (f"note: {name} was trained on {train_spp}-spp inputs and an EXR image holds no sample count; state "
                f"yours with --spp N to have it checked")
    if int(spp) != int(train_spp):
        return (f"warning: {name} was trained on {train_spp}-spp inputs and this input has {spp} spp; expect a "
                f"{'blurrier' if spp > train_spp else 'noisier'} result than it gives at {train_spp} spp (train one "
                f"at this count: python -m training train --spp {spp})")
    return None


def denoise_cli(a) -> int:
    from core.images import write_exr
    from .models.common import flush_denormals
    flush_denormals()
    if (a.input is None) == (a.store is None):
        raise ConfigError("give --input (an EXR image or a render-frame .npz) or --store S --frame I, not both")
    if a.store is not None and a.frame is None:
        raise ConfigError("--store needs --frame I (the frame index to denoise)")
    if a.store is None and a.frame is not None:
        raise ConfigError("--frame needs --store")
    if a.store is not None and any(getattr(a, g) for g in GUIDES):
        raise ConfigError("a store frame brings its own guides; --albedo/--normal/--depth go with --input")
    if a.tile and a.tile < 2 * TILE_ALIGN:
        raise ConfigError(f"--tile {a.tile}: at least {2 * TILE_ALIGN} pixels (0: automatic)")
    from .accel import pick_device, precision_for
    dev = pick_device(a.device)
    device, precision = str(dev), precision_for(a.precision, dev)
    model, spec, train_spp, name = load_method(a.checkpoint, device, compile=a.compile)
    stepwise = model is not None and getattr(model, "stepwise", False)
    t0 = time.perf_counter()
    if a.store is not None:
        if spec is None:             # OIDN on a store frame: the per-pixel mean of all its samples
            from .data import open_store
            spp = a.spp or int(open_store(a.store).layout.spp)
        else:
            spp = a.spp or train_spp
        items = items_from_store(spec, a.store, a.frame, spp, stepwise)
        src = f"frame {a.frame} of {a.store}" + (f" (after {len(items) - 1} frames of its clip)" if len(items) > 1 else "")
    elif a.input.endswith(".npz"):
        spp = a.spp or train_spp or 8
        items = items_from_npz(spec, a.input, spp)
        src = a.input
    else:
        items = items_from_exr(spec, a)
        src = a.input
    exr = a.store is None and not a.input.endswith(".npz")
    note = spp_note(spec, name, train_spp, a.spp, exr=exr)
    if note:
        print(note, file=sys.stderr)
    H, W = _check_sizes(items)
    out = denoise(model, items, tile=a.tile, device=device, progress=True, precision=precision)
    if not np.isfinite(out).all():
        raise DataError(f"{name} produced {int((~np.isfinite(out)).any(axis=-1).sum())} non-finite pixels on {src}")
    where = ""
    if exr:                         # the output keeps the input's place in its image
        from core.images import exr_windows, window_text
        data, display = exr_windows(a.input)
        write_exr(a.out, out, data_window=data, display_window=display)
        if data != display:
            where = f" at {window_text(data)} of {_size(display)}"
    else:
        write_exr(a.out, out)
    ms = (time.perf_counter() - t0) * 1e3
    print(f"{name}: {src} ({W}x{H}{where}) -> {a.out} in {ms:.0f} ms")
    return 0


__all__ = ["denoise", "denoise_cli", "items_from_exr", "items_from_npz", "items_from_store", "load_method",
           "run_sequence", "tiles", "AUTO_TILE_PIXELS", "TILE_MARGIN"]
