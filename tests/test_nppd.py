"""NPPD (Bálint et al. 2023): the paper's network sizes, the partitioning pyramid's filtering against explicit
loops and mass conservation, the recurrence, and training and clip-by-clip evaluation through the CLI at
2, 4 and 8 spp. The contract and stability tests (tests/test_models.py) cover it as a registered model."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from training.models import build
from training.models.nppd import K2, UP, upsample


def test_paper_defaults():
    m = build("nppd")
    assert m.input_spec().kind == "clips" and m.input_spec().default_spp == 8
    assert m.input_spec().features == ("normal", "depth", "albedo")        # what Noisebase holds, too
    convs = [c for c in m.encoder if isinstance(c, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size) for c in convs] == [(10, 32, (1, 1)), (32, 32, (1, 1)),
                                                                             (32, 32, (1, 1))]
    assert m.unet.cin == 70 and m.unet.depth == 5 and m.levels == 5
    assert m.unet.cout == 2 * K2 + 2 + 5 == 57 and all(h.out_channels == K2 + UP == 41 for h in m.heads)
    assert 14.5e6 < m.param_count() < 15.5e6                 # the paper's "15M" network
    assert m.train_defaults["loss"] == "smape-temporal" and m.train_defaults["lr"] == 1e-4
    assert build("nppd", size="small").param_count() < 0.3e6


def test_upsample_matches_an_explicit_loop_and_keeps_mass():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 5, 6, generator=g)
    w = 4.0 * F.softmax(torch.randn(2, UP, 5, 6, generator=g), dim=1)
    got = upsample(x, w)
    want = torch.zeros(2, 3, 12, 14)                            # one pixel of margin each side, cut below
    for cy in range(5):
        for cx in range(6):
            for t in range(UP):
                dy, dx = divmod(t, 4)
                want[:, :, 2 * cy + dy, 2 * cx + dx] += x[:, :, cy, cx] * w[:, t, cy, cx][:, None]
    torch.testing.assert_close(got, want[:, :, 1:-1, 1:-1])
    torch.testing.assert_close(want.sum(dim=(2, 3)), 4.0 * x.sum(dim=(2, 3)))


def test_the_pyramid_keeps_the_energy():
    """The partition sums to the colour, every kernel is a normalised splat, average pooling and the
    upsampling (weights summing to 4) undo each other in mass: whatever the logits, the output holds
    exactly the input's energy (none reaches the border here)."""
    torch.manual_seed(0)
    m = build("nppd", size="small", levels=4)
    colour = torch.zeros(1, 3, 64, 64)
    colour[..., 24:40, 24:40] = torch.rand(1, 3, 16, 16) * 5
    wts = [torch.randn(1, m.head0, 64, 64) * 3] + [torch.randn(1, K2 + UP, 64 // 2 ** i, 64 // 2 ** i) * 3
                                                   for i in range(1, 4)]
    out = m.pyramid(colour, wts)
    assert out.shape == colour.shape and (out >= 0).all()
    torch.testing.assert_close(out.sum(dim=(2, 3)), colour.sum(dim=(2, 3)), rtol=1e-5, atol=1e-4)
    assert not torch.allclose(out, colour, atol=1e-2)          # and it did filter


def test_the_state_carries_the_previous_frame():
    torch.manual_seed(0)
    m = build("nppd", **build("nppd").tiny).eval()
    from training.inputs import KINDS
    b = KINDS["clips"].example_batch(1, 2, 24, 20, frames=2, generator=torch.Generator().manual_seed(1))
    frame = lambda t, scale=1.0: {k: (v[:, t] * scale if k == "radiance" else v[:, t]) for k, v in b.items()}  # noqa: E731
    with torch.no_grad():
        _, s1, _ = m.step(frame(0), None)
        _, s2, _ = m.step(frame(0, 3.0), None)
        a = m.step(frame(1), s1)[0]
        c = m.step(frame(1), s2)[0]
        first = m.step(frame(1), None)[0]
    assert s1["history"].shape == (1, 6 + m.embed, 24, 20)
    assert not torch.allclose(a, c) and not torch.allclose(a, first)


@pytest.fixture(scope="module")
def clip_store(tmp_path_factory):
    from test_temporal import make_clip_store
    return make_clip_store(tmp_path_factory.mktemp("nppd") / "clips.zarr", clips=(2, 1, 1), frames=4, h=32, w=32)


def cli(*args) -> int:
    from training.__main__ import main
    return main([str(a) for a in args])


@pytest.mark.parametrize("spp", [2, 1])
def test_trains_by_bptt_and_evaluates_clip_by_clip(clip_store, tmp_path, spp):
    tiny = build("nppd").tiny
    run = tmp_path / "run"
    assert cli("train", "--model", "nppd", "--store", clip_store, "--out", run, "--steps", "3", "--batch", "2",
               "--crop", "16", "--spp", spp, "--val-every", "3", "--val-frames", "2", "--workers", "0",
               "--device", "cpu", "--no-progress", "--model-cfg", json.dumps({**tiny, "frames": 3})) == 0
    assert cli("evaluate", "--checkpoint", run / "checkpoint.pt", "--store", clip_store, "--split", "test",
               "--out", tmp_path / "e.json") == 0
    r = json.loads((tmp_path / "e.json").read_text())
    assert r["spp"] == spp and r["clips"] == 1 and len(r["frames"]) == 4
    assert all(math.isfinite(r["mean"][k]) for k in ("relmse", "psnr", "tpsnr", "ssim"))
    assert set(r["ci95"]) >= {"psnr", "tpsnr"}


def test_smape_temporal():
    from training.losses import build_loss
    loss = build_loss("smape-temporal")
    ref = torch.rand(2, 3, 3, 8, 8) + 0.1
    assert loss(ref, ref).item() == 0.0
    assert loss(ref * 2, ref * 2).item() == 0.0
    flicker = ref.clone()
    flicker[:, 1] *= 1.2
    steady = ref * 1.2 ** (1 / 3)
    assert loss(flicker, ref) > 0 and loss(steady, ref) > 0
    # a frame-to-frame flicker costs the temporal term too: more than its spatial share alone
    assert loss(flicker, ref).item() > 2.0 * (torch.abs(flicker - ref) / (flicker.abs() + ref.abs() + 1e-2)).mean().item()
    r = ref[:, 0] / (ref[:, 0].mean(dim=(1, 2, 3), keepdim=True) + 1e-8)     # each item over its reference's mean
    assert np.isclose(loss(ref[:, 0] * 1.1, ref[:, 0]).item(),
                      8 * (torch.abs(r * 0.1) / (r * 2.1 + 1e-2)).mean().item(), rtol=1e-4)
