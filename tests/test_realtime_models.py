"""The real-time per-pixel denoisers (nbg, wskpn), their inputs and temporal accumulation: math checked
against independent, explicit forms on tiny real tensors."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from training.models import build
from training.models._pixel import DEMOD_EPS, accumulate, demodulate, remodulate, warp
from training.models.nbg import bilateral_filter, corners, grid_shape
from training.models.wskpn import RepVGGBlock, box_filter, explicit_filter, explicit_kernels


# -- WSKPN ------------------------------------------------------------------------------------------

def test_fused_repvgg_block_equals_the_branches():
    torch.manual_seed(0)
    x = torch.randn(2, 6, 11, 9)
    for cin, cout, act in ((6, 6, True), (6, 4, True), (6, 6, False)):
        blk = RepVGGBlock(cin, cout, act)
        for p in blk.parameters():                 # non-trivial biases
            torch.nn.init.normal_(p, std=0.3)
        with torch.no_grad():
            assert (blk.fuse()(x[:, :cin]) - blk(x[:, :cin])).abs().max() < 1e-5


def test_wskpn_inference_form_is_fused_and_equal():
    torch.manual_seed(0)
    m = build("wskpn").eval()
    batch = m.input_spec().input_kind.example_batch(1, 1, 20, 18, generator=torch.Generator().manual_seed(1))
    fast = m.for_inference()
    assert all(isinstance(b, torch.nn.Sequential) for b in fast.net)
    assert sum(isinstance(c, torch.nn.Conv2d) for c in fast.modules()) == 6      # one 5x5 conv per block
    with torch.no_grad():
        assert (fast(batch) - m(batch)).abs().max() < 1e-5 * (1 + m(batch).abs().max())


@pytest.mark.parametrize("k", [3, 5, 13])
def test_box_form_equals_explicit_unfold_softmax(k):
    g = torch.Generator().manual_seed(k)
    r = torch.rand(2, 3, 15, 17, generator=g, dtype=torch.float64) * 5
    imp = torch.randn(2, 1, 15, 17, generator=g, dtype=torch.float64) * 3
    assert torch.allclose(box_filter(r, imp, k), explicit_filter(r, imp, k), rtol=1e-10, atol=1e-12)


def test_wskpn_weights_sum_to_one_with_importance_ratios():
    g = torch.Generator().manual_seed(0)
    imp = torch.randn(1, 1, 9, 8, generator=g, dtype=torch.float64) * 2
    k = 5
    w = explicit_kernels(imp, k)                                       # (1, 25, 9, 8)
    assert torch.allclose(w.sum(dim=1), torch.ones(1, 9, 8, dtype=torch.float64))
    # pixel p = (4, 4): taps t and t' are pixels q, q'; w_p(q) / w_p(q') = e^(I(q) - I(q'))
    p = (4, 4)
    for t, tt in ((0, 24), (3, 12), (7, 18)):
        q = (p[0] + t // k - 2, p[1] + t % k - 2)
        qq = (p[0] + tt // k - 2, p[1] + tt % k - 2)
        ratio = w[0, t, p[0], p[1]] / w[0, tt, p[0], p[1]]
        assert float(ratio) == pytest.approx(float(torch.exp(imp[0, 0, q[0], q[1]] - imp[0, 0, qq[0], qq[1]])),
                                             rel=1e-12)
    # a corner pixel: taps outside the frame get weight 0 and the rest still sum to 1 (no darkening)
    assert float(w[0, 0, 0, 0]) == 0.0 and float(w[0, :, 0, 0].sum()) == pytest.approx(1.0)
    r = torch.full((1, 3, 9, 8), 2.5, dtype=torch.float64)
    assert torch.allclose(box_filter(r, imp, k), r)                    # constant in, constant out, borders too


def test_box_form_survives_a_huge_importance_range():
    imp = torch.zeros(1, 1, 8, 8)
    imp[0, 0, :, :4] = -500.0                                          # 500 below the map's maximum
    out = box_filter(torch.ones(1, 3, 8, 8), imp, 3)
    assert torch.isfinite(out).all() and torch.allclose(out, torch.ones_like(out))


# -- NBG --------------------------------------------------------------------------------------------

def _dense_bilateral(values: np.ndarray, guide: np.ndarray, rate: int, guide_range: float) -> np.ndarray:
    """Brute force over every (pixel, cell) pair: eq. 10 splat, eq. 13 slice (tent weights)."""
    c, h, w = values.shape
    D, Hg, Wg = grid_shape(h, w, rate, guide_range)
    tent = lambda a: max(0.0, 1.0 - abs(a))                            # noqa: E731
    num = np.zeros((D, Hg, Wg, c))
    den = np.zeros((D, Hg, Wg))
    for y in range(h):
        for x in range(w):
            g = (guide[y, x] / rate, y / rate, x / rate)
            for cz in range(D):
                for cy in range(Hg):
                    for cx in range(Wg):
                        wt = tent(g[0] - cz) * tent(g[1] - cy) * tent(g[2] - cx)
                        if wt:
                            num[cz, cy, cx] += wt * values[:, y, x]
                            den[cz, cy, cx] += wt
    cell = np.where(den[..., None] > 0, num / np.where(den > 0, den, 1)[..., None], 0.0)
    out = np.zeros_like(values)
    for y in range(h):
        for x in range(w):
            g = (guide[y, x] / rate, y / rate, x / rate)
            acc, tot = np.zeros(c), 0.0
            for cz in range(D):
                for cy in range(Hg):
                    for cx in range(Wg):
                        wt = tent(g[0] - cz) * tent(g[1] - cy) * tent(g[2] - cx)
                        if wt and den[cz, cy, cx] > 0:
                            acc += wt * cell[cz, cy, cx]
                            tot += wt
            out[:, y, x] = acc / tot
    return out


def test_bilateral_grid_matches_a_brute_force_dense_splat_and_slice():
    rng = np.random.default_rng(0)
    vals = rng.random((3, 7, 6)) * 4
    guide = rng.random((7, 6)) * 30.0
    got = bilateral_filter(torch.from_numpy(vals)[None], torch.from_numpy(guide)[None], 4, 30.0)[0].numpy()
    # the smoothed |a| along the guide axis (sec. 4.2, eps 1e-7) moves weights by ~3e-4 at most
    assert np.allclose(got, _dense_bilateral(vals, guide, 4, 30.0), rtol=2e-3, atol=2e-3)


def test_bilateral_grid_gradcheck_float64():
    g = torch.Generator().manual_seed(0)
    vals = torch.rand(1, 2, 5, 4, generator=g, dtype=torch.float64, requires_grad=True)
    guide = (torch.rand(1, 5, 4, generator=g, dtype=torch.float64) * 14 + 0.3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v, gd: bilateral_filter(v, gd, 2, 16.0), (vals, guide),
                                    eps=1e-6, atol=1e-5)


def test_regions_more_than_two_bins_apart_do_not_leak():
    vals = torch.zeros(1, 3, 16, 16)
    vals[..., 8:] = 10.0                                               # bright right half
    guide = torch.full((1, 16, 16), 40.0)
    guide[..., 8:] = 40.0 + 2.5 * 4                                     # 2.5 bins apart at rate 4
    out = bilateral_filter(vals, guide, 4, 255.0)
    assert torch.equal(out[..., :8], torch.zeros_like(out[..., :8]))   # black stays black: no leak
    assert torch.allclose(out[..., 8:], torch.full_like(out[..., 8:], 10.0))


def test_an_empty_cell_has_zero_weight_not_zero_value():
    # black pixels sit in cells of their own: those cells are filled (weight > 0) with the value 0,
    # and slicing there returns exactly 0; a constant image is returned exactly (renormalised over the
    # filled corners only)
    vals = torch.full((1, 3, 12, 12), 3.0)
    guide = torch.rand(1, 12, 12, generator=torch.Generator().manual_seed(1)) * 255
    assert torch.allclose(bilateral_filter(vals, guide, 4, 255.0), vals)
    black = torch.zeros(1, 3, 12, 12)
    black[..., :6, :] = 5.0
    g2 = torch.where(torch.arange(12).view(1, 12, 1) < 6, 200.0, 20.0).expand(1, 12, 12).contiguous()
    out = bilateral_filter(black, g2, 4, 255.0)
    assert torch.equal(out[..., 6:, :], torch.zeros_like(out[..., 6:, :]))
    index, weight, (D, Hg, Wg) = corners(g2, 4, 255.0)
    from training.models.nbg import splat
    value, wsum = splat(black, index, weight, D * Hg * Wg)
    black_cells = index[:, 0, 9, 3]                                    # corners of a black pixel
    assert (wsum[black_cells][weight[:, 0, 9, 3] > 0] > 0).all()       # filled ...
    assert torch.equal(value[:, black_cells], torch.zeros_like(value[:, black_cells]))   # ... and black


def test_nbg_blend_weights_sum_to_one_and_guides_in_range():
    m = build("nbg")
    x = torch.rand(2, 10, 9, 7)
    with torch.no_grad():
        guides, blend = m.guides(x)
    assert guides.shape == (2, 3, 9, 7) and float(guides.min()) >= 0 and float(guides.max()) <= 255
    assert torch.allclose(blend.sum(dim=1), torch.ones(2, 9, 7))


# -- shared per-pixel parts --------------------------------------------------------------------------

def test_demodulation_is_undone_and_safe_for_zero_albedo():
    r = torch.rand(1, 3, 4, 4) * 3
    a = torch.rand(1, 3, 4, 4)
    a[..., 0, 0] = 0.0
    irr = demodulate(r, a)
    assert torch.isfinite(irr).all()
    assert torch.allclose(remodulate(irr, a), r, rtol=1e-6)
    assert torch.allclose(irr[..., 0, 0], r[..., 0, 0] / DEMOD_EPS)


def test_warp_zero_motion_is_identity_and_integer_motion_shifts():
    img = torch.rand(1, 3, 6, 7)
    zero = torch.zeros(1, 2, 6, 7)
    out, inside = warp(img, zero)
    assert torch.allclose(out, img, atol=1e-6) and inside.all()
    mot = torch.zeros(1, 2, 6, 7)
    mot[:, 0] = 2.0                                  # p_prev = p_cur + (2, -1): the point was 2 px right, 1 up
    mot[:, 1] = -1.0
    out, inside = warp(img, mot)
    assert torch.allclose(out[..., 1:, :5], img[..., :5, 2:], atol=1e-6)
    assert not inside[..., 0, :].any() and not inside[..., :, 5:].any()


def test_accumulation_blends_consistent_history_and_rejects_disocclusions():
    T, h, w = 3, 5, 6
    irr = torch.rand(1, T, 3, h, w)
    motion = torch.zeros(1, T, 2, h, w)
    depth = torch.ones(1, T, 1, h, w)
    normal = torch.zeros(1, T, 3, h, w)
    normal[:, :, 2] = 1.0
    depth[:, 2, :, :, :3] = 5.0                       # the left half changed surface in the last frame
    acc = accumulate(irr, motion, depth, normal, alpha=0.2)
    hist = irr[:, 0] * 0.2 + irr[:, 1] * 0.8
    want = hist * 0.2 + irr[:, 2] * 0.8
    assert torch.allclose(acc[..., 3:], want[..., 3:], atol=1e-6)
    assert torch.allclose(acc[..., :3], irr[:, 2, ..., :3])     # failed the depth test: current only


def test_temporal_models_read_windows_and_stills_models_do_not():
    m = build("nbg", temporal_frames=3, **build("nbg").tiny)
    spec = m.input_spec()
    assert (spec.kind, spec.frames, spec.default_spp) == ("pixels", 3, 1)
    batch = spec.input_kind.example_batch(2, 1, 12, 10, spec.frames)
    assert batch["radiance"].shape == (2, 3, 3, 12, 10)
    out = m(batch)
    assert out.shape == (2, 3, 12, 10) and torch.isfinite(out).all()
    assert build("wskpn").input_spec().frames == 1
