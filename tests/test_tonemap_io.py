"""core.images: the one tone map (the layer paper's eq. 7) that training, previews and exports
share, its display form, and OpenEXR files that round-trip."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from core import images as imageio

ROOT = Path(__file__).resolve().parent.parent

# srgb(log(1 + x)) worked by hand: log1p(1) = ln 2 -> 1.055 ln2^(1/2.4) - 0.055; 0.001 is on the linear
# segment (log1p(0.001) < 0.0031308 -> 12.92 log1p(0.001))
KNOWN = [(0.0, 0.0), (0.001, 0.012913544303439248), (0.5, 0.6692687482106934), (1.0, 0.850586073384777),
         (np.e - 1.0, 1.0), (100.0, 1.9402411615126838), (-3.0, 0.0)]


@pytest.mark.parametrize("x, y", KNOWN)
def test_tonemap_gives_known_values(x, y):
    assert float(imageio.tonemap(np.float64(x))) == pytest.approx(y, rel=1e-12, abs=1e-15)
    assert float(imageio.tonemap(torch.tensor(x, dtype=torch.float64))) == pytest.approx(y, rel=1e-12, abs=1e-15)


def test_tonemap_keeps_layout_dtype_and_gradients():
    x = np.array([[0.0, 0.002], [1.0, 1e5]], np.float32)
    y = imageio.tonemap(x)
    assert y.shape == x.shape and y.dtype == np.float32
    t = torch.tensor(x, requires_grad=True)
    yt = imageio.tonemap(t)
    assert yt.dtype == torch.float32 and torch.allclose(yt, torch.from_numpy(y), rtol=1e-6)
    yt.sum().backward()
    assert torch.isfinite(t.grad).all() and (t.grad > 0).all()      # finite at 0 (the linear segment)


def test_training_previews_and_exports_share_one_tone_map():
    """One module holds the tone map: the losses and metrics, the scene previews and the exports use it."""
    import scene_gen.commands as previews
    import stores.export as export
    import training.losses as losses
    import training.metrics as metrics
    assert losses.tonemap is metrics.tonemap is imageio.tonemap and previews.tonemap is imageio.display
    assert export.write_exr is imageio.write_exr
    x = np.array([0.0, 0.5, 1.0, 1.7, 50.0])
    np.testing.assert_allclose(imageio.display(x), np.clip(imageio.tonemap(x), 0, 1), rtol=1e-6)


def test_display_modes_and_non_finite_values():
    x = np.array([np.nan, np.inf, -np.inf, -1.0, 0.25, 1.0, 4.0])
    np.testing.assert_array_equal(imageio.to_srgb8(x), [0, 255, 0, 0, 130, 217, 255])
    np.testing.assert_array_equal(imageio.to_srgb8([0.0, 0.5, 2.0], mode="clamp"), [0, 188, 255])   # sRGB(0.5)
    np.testing.assert_array_equal(imageio.to_srgb8([0.0, 0.5, 2.0], mode="linear"), [0, 128, 255])
    np.testing.assert_array_equal(imageio.to_srgb8([0.5], exposure=2.0), imageio.to_srgb8([1.0]))
    with pytest.raises(ValueError, match="mode must be one of"):
        imageio.display(x, mode="reinhard")


def test_png_preview_is_the_tone_map(tmp_path):
    from PIL import Image
    img = np.linspace(0.0, 8.0, 4 * 5 * 3, dtype=np.float32).reshape(4, 5, 3)
    png = np.asarray(Image.open(imageio.write_png(tmp_path / "p" / "a.png", img)))
    np.testing.assert_array_equal(png, np.rint(np.clip(imageio.tonemap(img.astype(np.float64)), 0, 1) * 255))
    grey = np.asarray(Image.open(imageio.write_png(tmp_path / "g.png", img[..., :1])))
    assert grey.shape == (4, 5) and grey.dtype == np.uint8


def test_exr_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    rgb = (rng.random((6, 7, 3)) * 1e4).astype(np.float32)
    img, names = imageio.read_exr(imageio.write_exr(tmp_path / "d" / "rgb.exr", rgb))
    assert names == "RGB" and img.dtype == np.float32
    np.testing.assert_array_equal(img, rgb)
    np.testing.assert_array_equal(imageio.read_exr_channels(tmp_path / "d" / "rgb.exr")["RGB"], rgb)
    y = rgb[..., 0]
    imageio.write_exr(tmp_path / "y.exr", y, channels="Y")
    np.testing.assert_array_equal(imageio.read_exr_channels(tmp_path / "y.exr")["Y"], y)
    imageio.write_exr(tmp_path / "m.exr", rgb[..., :2], channels=["motion.x", "motion.y"])
    img, names = imageio.read_exr(tmp_path / "m.exr")
    assert names == "motion.x,motion.y"
    np.testing.assert_array_equal(img, rgb[..., :2])
    half, _ = imageio.read_exr(imageio.write_exr(tmp_path / "h.exr", rgb / 1e4, half=True))
    np.testing.assert_allclose(half, rgb / 1e4, rtol=1e-3)
    with pytest.raises(ValueError, match=r"h\.exr: image of shape \(6, 7, 3\) does not have the 2 channels"):
        imageio.write_exr(tmp_path / "h.exr", rgb, channels="RG")


def test_imageio_does_not_import_torch():
    code = "import sys, core.images, core.checks, core.errors, core.variant; assert 'torch' not in sys.modules, 'torch imported'"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
