"""Images: the one tone map of the project, its display form, and OpenEXR / PNG files (numpy only).

The tone map is the layer-embedding paper's (Munkberg & Hasselgren 2020, eqs. 7-8):
``tonemap(x) = srgb(log(max(x, 0) + 1))`` with the sRGB transfer function ``srgb``. Training
(losses, PSNR/SSIM), the scene previews and the store exports all use it, so a preview shows the
values a model is scored on. It is element-wise on numpy arrays of any layout, and on torch tensors
(differentiable) when the caller passes one; this module imports numpy only (torch is never imported
here). It lives in ``core``, the package the others build on, and imports nothing of the project.

:func:`display` is the tone map for a screen: an ``exposure`` scale, non-finite values made finite
(NaN -> 0, +Inf -> 1), then ``mode`` ``"log"`` (the tone map), ``"clamp"`` (the sRGB curve of the value
clipped to [0, 1]: albedo) or ``"linear"`` (no curve: normal maps as ``n * 0.5 + 0.5``), clipped to
[0, 1]. No auto exposure: a preview shows the radiance levels the dataset stores.

OpenEXR files (the ``OpenEXR`` package; scanline, ZIP): :func:`write_exr` / :func:`read_exr` for images
(float32 HWC with channel names) and :func:`read_exr_channels` for the channels by name. The readers
give the pixels of a file's data window; :func:`exr_windows` says where that window lies in the display
window, and :func:`write_exr` writes both windows (``data_window``, ``display_window``).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

SRGB_A = 0.055
SRGB_THRESHOLD = 0.0031308
MODES = ("log", "clamp", "linear")


def _namespace(x):
    """(torch, x) for a torch tensor, else (numpy, x as an array). torch is looked up, not imported:
    a tensor can only exist once torch is loaded."""
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(x, torch.Tensor):
        return torch, x
    return np, np.asarray(x)


def srgb(x):
    """The sRGB transfer function Gamma (eq. 8), element-wise, for x >= 0 (numpy or torch, same layout)."""
    xp, x = _namespace(x)
    # clamp inside the power so the branch not taken has a finite gradient at 0
    hi = (1.0 + SRGB_A) * x.clip(min=SRGB_THRESHOLD) ** (1.0 / 2.4) - SRGB_A
    return xp.where(x > SRGB_THRESHOLD, hi, 12.92 * x)


def tonemap(x):
    """Eq. 7: ``srgb(log(max(x, 0) + 1))``. Radiance (float, any layout; numpy or torch) -> tone-mapped,
    same layout and dtype, not clipped (1 at x = e - 1). Negative radiance is clamped to 0 first
    (radiance is non-negative; the clamp keeps ``log`` defined for slightly negative denoiser outputs)."""
    xp, x = _namespace(x)
    return srgb(xp.log1p(x.clip(min=0.0)))


def display(image, exposure: float = 1.0, mode: str = "log") -> np.ndarray:
    """HDR image (any layout) -> display values in [0, 1] (float32, same layout); see the module
    docstring for ``mode``. NaN shows as 0, +Inf as 1, -Inf as 0."""
    if mode not in MODES:
        raise ValueError(f"tone map mode must be one of {MODES}, got {mode!r}")
    x = np.nan_to_num(np.asarray(image, np.float64) * exposure, nan=0.0, posinf=1e30, neginf=0.0)
    if mode == "log":
        y = tonemap(x)
    elif mode == "clamp":
        y = srgb(np.clip(x, 0.0, 1.0))
    else:
        y = x
    return np.clip(y, 0.0, 1.0).astype(np.float32)


def to_srgb8(image, exposure: float = 1.0, mode: str = "log") -> np.ndarray:
    """:func:`display` as 8-bit values (uint8, same layout), rounded to nearest."""
    return np.rint(display(image, exposure, mode) * 255.0).astype(np.uint8)


def write_png(path: str | Path, image, exposure: float = 1.0, mode: str = "log") -> Path:
    """Write ``image`` (HDR float, HW, HW1 or HW3) through :func:`to_srgb8` as an 8-bit PNG."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    Image.fromarray(to_srgb8(img, exposure, mode)).save(path)
    return path


Window = tuple[int, int, int, int]       # (x0, y0, x1, y1), inclusive: OpenEXR's box2i


def write_exr(path: str | Path, image, channels="RGB", half: bool = False, *, data_window: Window | None = None,
              display_window: Window | None = None) -> Path:
    """Write ``image`` (float32, HWC or HW) as a scanline, ZIP-compressed OpenEXR file. ``channels``
    names the C channels: a string of one-letter names (``"RGB"``, ``"Y"``, ``"RG"``) or a list of
    names. ``half``: store float16. ``data_window``: where the image's pixels lie, ``(x0, y0, x1, y1)``
    inclusive, the image's size (default: at (0, 0)); ``display_window``: the whole image's (default: the
    data window)."""
    import OpenEXR

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(channels)
    img = np.asarray(image, dtype=np.float16 if half else np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] != len(names):
        raise ValueError(f"{path}: image of shape {img.shape} does not have the {len(names)} channels "
                         f"named {names}")
    chans = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    H, W = img.shape[:2]
    data = tuple(int(v) for v in data_window) if data_window is not None else (0, 0, W - 1, H - 1)
    if (data[2] - data[0] + 1, data[3] - data[1] + 1) != (W, H):
        raise ValueError(f"{path}: data window {window_text(data)} is not the image's {W}x{H}")
    if data_window is not None or display_window is not None:
        box = lambda b: (np.array(b[:2], np.int32), np.array(b[2:], np.int32))      # noqa: E731
        header["dataWindow"] = box(data)
        header["displayWindow"] = box(tuple(int(v) for v in display_window) if display_window is not None else data)
    with OpenEXR.File(header, chans) as f:
        try:
            f.write(str(path))
        except RuntimeError as e:         # OpenEXR's bindings raise a RuntimeError with the system's text
            import errno
            import os
            for code in (errno.ENOSPC, errno.EDQUOT):   # a full disk is an OSError, as every other writer's
                if os.strerror(code).lower() in str(e).lower():
                    raise OSError(code, os.strerror(code), str(path)) from e
            raise
    return path


def read_exr_channels(path: str | Path) -> dict:
    """An OpenEXR file's channels: name -> pixels (HW), with R, G, B (and A) grouped by OpenEXR as
    ``"RGB"`` / ``"RGBA"`` -> HWC when all are present."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return {k: np.array(v.pixels) for k, v in f.channels().items()}


def exr_windows(path: str | Path) -> tuple[Window, Window]:
    """``(data window, display window)`` of an OpenEXR file, each ``(x0, y0, x1, y1)`` inclusive: where
    the pixels the readers give lie, and the whole image they belong to."""
    import OpenEXR

    with OpenEXR.File(str(path), header_only=True) as f:
        h = f.header()
        return tuple(tuple(int(v) for b in h[k] for v in b) for k in ("dataWindow", "displayWindow"))


def window_text(w: Window) -> str:
    """``(x0,y0)-(x1,y1)``, as OpenEXR's tools print a window."""
    return f"({w[0]},{w[1]})-({w[2]},{w[3]})"


def exr_channel_names(path: str | Path) -> list[str]:
    """The channel names of an OpenEXR file (as the file lists them: sorted by name)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        return list(f.channels().keys())


def read_exr_named(path: str | Path, names) -> np.ndarray:
    """The channels ``names`` of an OpenEXR file, in that order, as float32 HWC (KeyError for a name the
    file does not have)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in names], axis=-1)


def read_exr(path: str | Path) -> tuple[np.ndarray, str]:
    """An OpenEXR image as (float32 HWC, channel names): R, G, B, A first, then the others in file order;
    the names joined as ``"RGB"`` when all are one letter, else with commas."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        names = list(ch.keys())
        order = [c for c in "RGBA" if c in names] + [c for c in names if c not in "RGBA"]
        img = np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in order], axis=-1)
    return img, "".join(order) if all(len(c) == 1 for c in order) else ",".join(order)
