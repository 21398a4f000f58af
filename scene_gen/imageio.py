"""Image files: OpenEXR (the ``OpenEXR`` package) and tone-mapped PNG previews. numpy only.

Tone mapping for previews is fixed (no per-image auto exposure): ``exposure`` scale, then
``log(1 + x)`` compression (the layer paper's eq. 7) or a plain clamp, then sRGB encoding.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_exr(path: str | Path, image: np.ndarray, channels: str = "RGB", half: bool = False) -> Path:
    """Write ``image`` (float32, HWC or HW) as a scanline OpenEXR file; channel names from ``channels``."""
    import OpenEXR

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, dtype=np.float16 if half else np.float32)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] != len(channels):
        raise ValueError(f"image has {img.shape[-1]} channels, names given for {len(channels)}: {channels!r}")
    chans = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate(channels)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, chans) as f:
        f.write(str(path))
    return path


def read_exr(path: str | Path) -> tuple[np.ndarray, str]:
    """Read an OpenEXR file; returns (float32 HWC, channel names in order)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        names = list(ch.keys())
        order = [c for c in "RGBA" if c in names] + [c for c in names if c not in "RGBA"]
        img = np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in order], axis=-1)
    return img, "".join(order) if all(len(c) == 1 for c in order) else ",".join(order)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def tonemap(image: np.ndarray, exposure: float = 1.0, mode: str = "log") -> np.ndarray:
    """HDR float image → display values in [0, 1] (float32). NaN/Inf show as 0 / 1."""
    x = np.nan_to_num(np.asarray(image, np.float64) * exposure, nan=0.0, posinf=1e30, neginf=0.0)
    x = np.maximum(x, 0.0)
    if mode == "log":
        x = np.log1p(x)
    elif mode != "clamp":
        raise ValueError(f"tone map mode must be 'log' or 'clamp', got {mode!r}")
    return srgb_encode(x).astype(np.float32)


def write_png(path: str | Path, image: np.ndarray, exposure: float = 1.0, mode: str = "log") -> Path:
    """Tone-map an HDR (HWC, 1 or 3 channels) image and write an 8-bit PNG."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    ldr = (tonemap(img, exposure, mode) * 255.0 + 0.5).astype(np.uint8)
    Image.fromarray(ldr).save(path)
    return path
