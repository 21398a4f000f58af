"""Metrics against independent implementations (scikit-image, hand-computed values) on real images."""
from __future__ import annotations

import numpy as np
import pytest
import skimage.data
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from training import metrics
from core.images import tonemap


@pytest.fixture(scope="module")
def images():
    ref = skimage.data.astronaut()[100:196, 150:246].astype(np.float64) / 255.0     # real photo, 96x96
    rng = np.random.default_rng(0)
    noisy = np.clip(ref + rng.normal(0.0, 0.08, ref.shape), 0.0, 1.0)
    return ref, noisy


def test_tonemap_matches_the_srgb_formula():
    x = np.array([0.0, 1e-3, 0.5, 1.0, 10.0, 1e8])
    y = np.log1p(x)
    expected = np.where(y <= 0.0031308, 12.92 * y, 1.055 * y ** (1 / 2.4) - 0.055)
    assert np.allclose(tonemap(x), expected)
    assert tonemap(np.array(np.e - 1.0)) == pytest.approx(1.0)


def test_psnr_and_ssim_match_scikit_image(images):
    ref, noisy = images
    assert metrics.psnr_ldr(noisy, ref) == pytest.approx(peak_signal_noise_ratio(ref, noisy, data_range=1.0), rel=1e-12)
    sk = structural_similarity(ref, noisy, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                               use_sample_covariance=False)
    assert metrics.ssim_ldr(noisy, ref) == pytest.approx(sk, abs=1e-12)
    # the value the hand-written SSIM (separable 11x11 Gaussian, valid pixels) gave before scikit-image
    # computed it: the reports' SSIM is unchanged, and a change of window or covariance would show here
    assert metrics.ssim_ldr(noisy, ref) == pytest.approx(0.49819433065921, abs=1e-12)
    assert metrics.ssim_ldr(noisy[..., 0], ref[..., 0]) == pytest.approx(0.47654734617452, abs=1e-12)   # (H, W)


def test_ssim_on_known_inputs():
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 1.0, (24, 24, 3))
    assert metrics.ssim_ldr(x, x) == 1.0
    # two flat images: no variance, so SSIM is the luminance term (2ab + C1) / (a^2 + b^2 + C1), C1 = (0.01 L)^2
    a, b, c1 = 0.25, 0.5, 0.01 ** 2
    flat = metrics.ssim_ldr(np.full((16, 16, 3), a), np.full((16, 16, 3), b))
    assert flat == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), abs=1e-12)
    # the same on a data range of 2: C1 four times as large
    flat2 = metrics.ssim_ldr(np.full((16, 16, 3), a), np.full((16, 16, 3), b), data_range=2.0)
    assert flat2 == pytest.approx((2 * a * b + 4 * c1) / (a * a + b * b + 4 * c1), abs=1e-12)
    with pytest.raises(ValueError, match="at least 11 px"):
        metrics.ssim_ldr(np.zeros((10, 32, 3)), np.zeros((10, 32, 3)))


def test_hdr_metrics_tonemap_first(images):
    ref, noisy = images
    lin_ref, lin_noisy = np.expm1(ref) * 3.0, np.expm1(noisy) * 3.0   # HDR radiance
    tr, tn = tonemap(lin_ref), tonemap(lin_noisy)
    assert metrics.psnr(lin_noisy, lin_ref) == pytest.approx(peak_signal_noise_ratio(tr, tn, data_range=1.0))
    assert metrics.ssim(lin_noisy, lin_ref) == pytest.approx(metrics.ssim_ldr(tn, tr), abs=1e-15)
    assert metrics.ssim(lin_noisy, lin_ref) == pytest.approx(0.55055337395143, abs=1e-12)
    assert metrics.ssim(lin_ref, lin_ref) == 1.0
    assert metrics.psnr(lin_ref, lin_ref) == float("inf")


def test_relmse_and_smape_by_hand():
    r = np.array([[[1.0, 0.0, 2.0]]])
    d = np.array([[[2.0, 0.1, 2.0]]])
    assert metrics.relmse(d, r) == pytest.approx(np.mean([1.0 / 1.01, 0.01 / 0.01, 0.0]))
    assert metrics.smape(d, r) == pytest.approx(np.mean([1.0 / 3.01, 0.1 / 0.11, 0.0]))


def test_tpsnr_uses_temporal_differences(images):
    ref, noisy = images
    clip_ref = np.stack([ref, ref * 0.9, ref * 0.8])
    # a constant offset in every frame: per-frame PSNR finite, temporal differences identical
    clip_d = clip_ref + 0.05
    assert metrics.tpsnr(clip_d, clip_ref) > 35.0
    flicker = np.stack([noisy, ref * 0.9, noisy * 0.8])
    assert metrics.tpsnr(flicker, clip_ref) < metrics.tpsnr(clip_d, clip_ref) - 5.0
    td, tr = np.diff(tonemap(flicker), axis=0), np.diff(tonemap(clip_ref), axis=0)
    assert metrics.tpsnr(flicker, clip_ref) == pytest.approx(10 * np.log10(1.0 / np.mean((td - tr) ** 2)))


def test_flip_orders_errors(images):
    ref, noisy = images
    lin_ref = np.expm1(ref) * 2.0
    assert metrics.flip(lin_ref, lin_ref) == pytest.approx(0.0, abs=1e-6)
    small = metrics.flip(lin_ref * 1.05, lin_ref)
    big = metrics.flip(np.expm1(noisy) * 2.0, lin_ref)
    assert 0.0 < small < big < 1.0


def test_flip_of_a_black_reference_does_not_end_the_process():
    """flip-evaluator takes HDR exposures from the reference and exits the process on a black one (the
    hard-case ``black``): black against black is 0, anything else a large error."""
    import numpy as np
    from training.metrics import flip
    black = np.zeros((16, 16, 3), np.float32)
    assert flip(black, black) == 0.0
    grey = np.full((16, 16, 3), 0.5, np.float32)
    assert 0.5 < flip(grey, black) <= 1.0
    # the exposures follow the test image, so the error does not depend on its scale
    assert abs(flip(grey * 0.01, black) - flip(grey, black)) < 1e-4
