"""The temporal adaptive sampler and recurrent denoiser (Hasselgren et al. 2020): eq. 2's budget, the
composition of stored sample layers and its gradient, warping against a rendered clip, eq. 3, eq. 4,
backpropagation through time, stability, and training/evaluation on a real store of moving clips."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from training import adaptive
from training.losses import build_loss
from training.logspace import squeeze, unsqueeze
from training.models import build
from training.models._pixel import warp
from training.models.temporal import apply_kernel, combine_scales, down

LEVELS = 6
CAP = 2 ** LEVELS - 1


def tiny(name="temporal", **kw):
    torch.manual_seed(0)
    cls = build(name)
    return build(name, **{**cls.tiny, **kw})


def layer_batch(b=2, T=3, h=16, w=12, spp=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    m = build("temporal")
    spec = m.input_spec()
    batch = spec.input_kind.example_batch(b, spp, h, w, T, g)
    batch["reference"] = torch.rand(b, T, 3, h, w, generator=g)
    return batch


# ------------------------------------------------------------------------------------ eq. 2 budget
def test_constant_map_gives_exactly_n_everywhere():
    for n in (1, 4, 7, 63):
        cont, counts = adaptive.sample_counts(torch.full((2, 1, 9, 11), 0.37), n, CAP)
        assert (counts == n).all(), n


@pytest.mark.parametrize("scale", [0.5, 3.0, 12.0])
def test_random_map_meets_the_budget_within_rounding_and_the_cap(scale):
    g = torch.Generator().manual_seed(1)
    logits = torch.randn(3, 1, 20, 17, generator=g) * scale       # 12: most mass on a few pixels
    m = 20 * 17
    for n in (1, 4, 16):
        cont, counts = adaptive.sample_counts(logits, n, CAP)
        assert counts.min() >= 0 and counts.max() <= CAP
        total = counts.sum(dim=(1, 2, 3)).double()
        assert torch.all((total - m * n).abs() <= m / 2), (total, m * n)
        assert torch.allclose(cont.sum(dim=(1, 2, 3)).double(), torch.tensor(float(m * n)).double(), rtol=1e-4)


def test_budget_out_of_range_is_refused():
    from stores.errors import SampleCountError
    with pytest.raises(SampleCountError, match="budget"):
        adaptive.sample_counts(torch.zeros(1, 1, 4, 4), 64, CAP)


# ------------------------------------------------------------------------------------ composition
def _numpy_compose(layers: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """An independent composition in numpy, float64, bit by bit: ``layers (L 3 h w)``, ``counts (h w)``."""
    total = np.zeros(layers.shape[1:], np.float64)
    for n in range(layers.shape[0]):
        total += layers[n].astype(np.float64) * (((counts >> n) & 1) * 2.0 ** n)[None]
    return np.where(counts[None] > 0, total / np.maximum(counts, 1)[None], 0.0).astype(np.float32)


def test_every_count_composes_the_sample_weighted_mean_of_exactly_its_layers():
    g = torch.Generator().manual_seed(2)
    layers = torch.rand(1, LEVELS, 3, 8, 8, generator=g) * 10
    counts = torch.arange(64).view(1, 1, 8, 8)
    got = adaptive.compose(layers, counts)[0].numpy()
    for c in range(64):
        y, x = divmod(c, 8)
        used = [l for l in range(LEVELS) if c >> l & 1]
        want = sum(2 ** l * layers[0, l, :, y, x] for l in used) / max(c, 1) if used else torch.zeros(3)
        np.testing.assert_allclose(got[:, y, x], want.numpy(), rtol=1e-5, atol=1e-6)
    # an independent numpy composition agrees everywhere
    np.testing.assert_allclose(got, _numpy_compose(layers[0].numpy(), counts[0, 0].numpy()), rtol=1e-5, atol=1e-6)
    const = torch.full((1, LEVELS, 3, 8, 8), 2.5)
    out = adaptive.compose(const, counts)
    assert torch.allclose(out[..., counts[0, 0] > 0], torch.tensor(2.5)) and (out[..., counts[0, 0] == 0] == 0).all()


def test_renderer_gradient_is_the_dasr_approximation():
    g = torch.Generator().manual_seed(3)
    layers = torch.rand(1, LEVELS, 3, 4, 4, generator=g)
    cont = torch.tensor([0.0, 1.0, 5.0, 13.0, 62.0, 63.0, 2.0, 4.0] * 2).view(1, 1, 4, 4).requires_grad_()
    counts = torch.round(cont.detach()).long()
    c = adaptive.compose(layers, counts, cont)
    c.sum().backward()
    for (y, x) in [(0, 0), (0, 3), (1, 0), (1, 1)]:
        s = int(counts[0, 0, y, x])
        used = [l for l in range(LEVELS) if s >> l & 1]
        unused = [l for l in range(LEVELS) if not s >> l & 1]
        mean = lambda ls: sum(2 ** l * layers[0, l, :, y, x] for l in ls) / max(sum(2 ** l for l in ls), 1)  # noqa: E731
        cu = mean(unused) if unused else mean(used)
        want = ((cu - (mean(used) if used else 0)) / (s + 1)).sum()
        assert torch.isclose(cont.grad[0, 0, y, x], want, atol=1e-6), (s, cont.grad[0, 0, y, x], want)
    assert cont.grad[0, 0, 1, 1] == 0                  # 63: at the cap, no unused layer


def test_sampler_receives_gradient_through_the_renderer():
    m = tiny()
    batch = layer_batch()
    out = m(batch)
    build_loss("l1-temporal")(out, batch["reference"]).backward()
    g = sum(p.grad.abs().sum() for p in m.sampler.parameters() if p.grad is not None)
    assert torch.isfinite(g) and g > 0


# ------------------------------------------------------------------------------------ warping
def test_warp_identity_and_integer_shift():
    img = torch.rand(1, 3, 7, 9)
    assert torch.allclose(warp(img, torch.zeros(1, 2, 7, 9))[0], img, atol=1e-6)
    mot = torch.zeros(1, 2, 7, 9)
    mot[:, 0], mot[:, 1] = -3.0, 2.0
    out = warp(img, mot)[0]
    assert torch.equal(out[..., :5, 3:], img[..., 2:, :6])


def test_warp_sign_matches_a_rendered_moving_clip(mi):
    """Warping frame 0 (its albedo guide) by frame 1's stored motion reproduces frame 1 better than
    the opposite sign or no warp, on a textured floor seen from a moving camera."""
    from pipeline.render import RenderConfig, render_frame
    from scene_gen.spec import (CameraSpec, LightSpec, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, TextureSpec,
                                Transform)
    tex = TextureSpec("checker", (0.05, 0.05, 0.05), (0.9, 0.9, 0.9), uv_scale=1.5)
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse", texture=tex),
                       transform=Transform(translate=(0.0, -1.0, 0.0), scale=(6.0, 1.0, 6.0)))
    cams = tuple(CameraSpec(origin=(0.5 * f, 3.0, 4.0), target=(0.0, -1.0, 0.0), fov=50.0) for f in range(2))
    spec = SceneSpec("outdoor", 5, (floor,), (LightSpec("constant", {"radiance": (1.0, 1.0, 1.0)}),), cams)
    c = RenderConfig(res=(32, 24), spp=4, ref_spp=16, ref_passes=4, ref_min_passes=4, layer_levels=0)
    f0, f1 = render_frame(spec, 0, c), render_frame(spec, 1, c)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))[None].float()   # noqa: E731
    a0, a1, m = t(f0["guides_albedo"]), t(f1["guides_albedo"]), t(f1["guides_motion"])
    assert m.abs().max() > 1.5
    errs = {}
    for sign in (1.0, -1.0, 0.0):
        out, inside = warp(a0, sign * m)
        errs[sign] = float(((out - a1).abs() * inside).sum() / inside.sum())
    assert errs[1.0] < 0.5 * errs[0.0] and errs[1.0] < 0.5 * errs[-1.0], errs


# ------------------------------------------------------------------------------------ eq. 3 and kernels
def test_scale_composition_with_coarse_equal_to_downsampled_fine_returns_fine():
    g = torch.Generator().manual_seed(4)
    fine = torch.rand(2, 3, 8, 12, generator=g)
    alpha = torch.rand(2, 1, 4, 6, generator=g)
    assert torch.allclose(combine_scales(fine, down(fine), alpha), fine, atol=1e-6)
    coarse = torch.rand(2, 3, 4, 6, generator=g)
    full = combine_scales(fine, coarse, torch.ones(2, 1, 4, 6))       # alpha 1: the coarse image's mean
    assert torch.allclose(down(full), coarse, atol=1e-6)


def test_kernels_are_normalised_and_a_centre_tap_is_the_identity():
    x = torch.rand(1, 3, 6, 6)
    logits = torch.full((1, 25, 6, 6), -80.0)
    logits[:, 12] = 80.0
    assert torch.allclose(apply_kernel(x, logits), x, atol=1e-6)
    assert torch.allclose(apply_kernel(torch.full_like(x, 0.7), torch.randn(1, 25, 6, 6)), torch.tensor(0.7))


# ------------------------------------------------------------------------------------ eq. 4, BPTT
def test_temporal_loss_is_zero_for_equal_differences_and_reaches_earlier_frames():
    loss = build_loss("l1-temporal")
    ref = torch.rand(2, 4, 3, 5, 5) * 3
    shifted = unsqueeze(squeeze(ref) + 0.1)            # equal frame differences in log space, offset 0.1
    assert abs(float(loss(shifted, ref)) - 0.1) < 1e-4   # the spatial term only
    assert float(loss(ref, ref)) < 1e-6
    m = tiny()
    batch = layer_batch(T=3)
    batch["albedo"].requires_grad_()
    out = m(batch)
    loss(out, batch["reference"]).backward()
    g = batch["albedo"].grad
    assert g[:, 1].abs().sum() > 0                      # frame 1 reaches the loss only through the history
    assert g[:, 0].abs().sum() == 0                     # frame 0 only seeds the history with noisy radiance


def test_variants_and_inputs():
    assert build("temporal").input_spec().frames == 5 and build("temporal").input_spec().default_spp == 4
    assert build("temporal-perframe").input_spec().frames == 1
    m = tiny("temporal-uniform")
    assert m.sampler is None
    batch = layer_batch(T=3)
    _, _, extra = m.step({k: v[:, 1] if v.dim() > 2 and k != "layer_spp" else v for k, v in batch.items()},
                         {"history": torch.rand(2, 3, 16, 12)})
    assert (extra["counts"] == 4).all()
    from training.errors import ConfigError
    with pytest.raises(ConfigError, match="size"):
        build("temporal", size="huge")


# ------------------------------------------------------------------------------------ stability
@pytest.mark.parametrize("case", ["fireflies", "black", "nan", "zero-samples"])
def test_stability_forward_and_backward(case):
    m = tiny()
    batch = layer_batch(T=3)
    lay = batch["layers"]
    if case == "fireflies":
        lay[..., ::3, ::4] = 1e6
    elif case == "black":
        lay.zero_()
        batch["albedo"].zero_()
    elif case == "nan":
        lay[..., 2:5, 3] = float("nan")
        lay[:, :, 0, :, 0, 0] = float("inf")
    elif case == "zero-samples":                       # a map that starves most pixels
        for p in m.sampler.final.parameters():
            torch.nn.init.zeros_(p)
        with torch.no_grad():
            m.sampler.final.bias.fill_(0.0)
        batch["spp"] = torch.full((2,), 0.2)          # 0.2 spp on average: most pixels get 0 samples
    out = m(batch)
    assert torch.isfinite(out).all()
    build_loss("l1-temporal")(out, batch["reference"]).backward()
    for name, p in m.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    if case == "zero-samples":
        frame = {k: (v[:, 2] if k in ("layers", "albedo", "normal", "depth", "motion") else v) for k, v in batch.items()}
        _, _, extra = m.step(frame, {"history": squeeze(out[:, 1])})
        assert (extra["counts"] == 0).float().mean() > 0.5


def test_a_forward_makes_no_tensor_from_host_values(monkeypatch):
    """No tensor is built from Python values inside the model: on a GPU each would be a host-to-device
    copy at every call (the grey weights were one)."""
    m = tiny()
    batch = layer_batch(T=3)

    def refusing(real):
        def make(data, *a, **k):
            if not isinstance(data, torch.Tensor):
                raise AssertionError(f"a tensor made from host values {data!r} inside the model's forward")
            return real(data, *a, **k)
        return make
    for name in ("tensor", "as_tensor"):
        monkeypatch.setattr(torch, name, refusing(getattr(torch, name)))
    assert torch.isfinite(m(batch)).all()


# ------------------------------------------------------------------------------------ real store
def make_clip_store(path, clips=(2, 1, 1), frames=4, h=16, w=16):
    from stores.schema import StoreLayout
    from stores.writer import open_or_create
    from test_stores_synthetic import synthetic_frame
    from test_training import seeds_by_split
    seeds = seeds_by_split(clips, start=100)
    layout = StoreLayout(num_frames=len(seeds) * frames, height=h, width=w, spp=2, tile=16)
    writer = open_or_create(str(path), layout, {"test": True})
    i = 0
    for s in seeds:
        for f in range(frames):
            writer.write_frame(i, synthetic_frame(s, h, w, 2, frame=f, num_frames=frames, motion=True, sun=False,
                                                  scene_seed=s))
            i += 1
    return str(path)


@pytest.fixture(scope="module")
def clip_store(tmp_path_factory):
    return make_clip_store(tmp_path_factory.mktemp("clips") / "clips.zarr")


def test_train_and_evaluate_clip_by_clip(clip_store, tmp_path):
    from training.config import TrainConfig
    from training.evaluate import evaluate, write_json
    from training.loop import train
    m = build("temporal")
    cfg = TrainConfig(model="temporal", model_cfg={**m.tiny, "frames": 3}, steps=3, batch=2, crop=16, val_every=3,
                      val_frames=2, val_crop=16, log_every=1, checkpoint_every=3, seed=1, workers=0)
    assert (cfg.loss, cfg.lr, cfg.spp) == ("l1-temporal", 1e-3, 4)
    res = train(cfg, clip_store, tmp_path / "run", progress=False)
    assert res["step"] == 3 and np.isfinite(res["loss"]) and np.isfinite(res["val"]["psnr"])
    r = evaluate(tmp_path / "run" / "checkpoint.pt", clip_store, split="test", with_flip=False)
    assert r["spp"] == 4 and len(r["frames"]) == 4 and r["clips"] == 1
    assert abs(r["mean"]["spp"] - 4) <= 0.5 and np.isfinite(r["mean"]["tpsnr"])
    assert all(abs(f["spp"] - 4) <= 0.5 for f in r["frames"])
    assert r["sample_map"]["counts"].shape == (16, 16)
    write_json(r, tmp_path / "e.json")
    saved = json.loads((tmp_path / "e.json").read_text())
    assert {"tpsnr", "spp"} <= set(saved["mean"]) and saved["sample_map"]["index"] == r["frames"][-1]["index"]
    # a baseline at the same budget, on the same frames
    b = evaluate("input", clip_store, split="test", spp=2, with_flip=False)
    assert b["mean"]["spp"] == 2 and np.isfinite(b["mean"]["tpsnr"])
    with pytest.raises(Exception, match="samples per pixel"):
        evaluate(tmp_path / "run" / "checkpoint.pt", clip_store, split="test", spp=64, with_flip=False)


def test_report_shows_tpsnr_spp_and_the_sample_map(clip_store, tmp_path):
    from training.config import TrainConfig
    from training.loop import train
    from training.report import report
    m = build("temporal")
    cfg = TrainConfig(model="temporal", model_cfg={**m.tiny, "frames": 2}, steps=2, batch=2, crop=16, val_every=0,
                      val_frames=1, val_crop=16, log_every=1, checkpoint_every=2, seed=2, workers=0)
    train(cfg, clip_store, tmp_path / "runs" / "temporal", progress=False)
    res = report([tmp_path / "runs" / "temporal"], clip_store, tmp_path / "rep", with_flip=False, progress=False,
                 clips_store=clip_store)
    labels = [r["label"] for r in res["results"]]
    assert [r["label"] for r in res["clips"]] == labels and res["clips"][1]["clips"] == 1   # the clips section
    assert res["clips"][1]["mean"]["tpsnr"] == pytest.approx(res["results"][1]["mean"]["tpsnr"])
    assert labels == ["input", "temporal", "oidn"]                       # baselines at the run's 4 spp
    assert all(r["spp"] == 4 for r in res["results"])
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "tPSNR" in text and "| spp |" in text and "## Moving clips" in text
    for name in ("speed_vs_error.png", "crops.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 1000
    maps = list((tmp_path / "rep").glob("sample_map-*.png"))
    # a sampler that has not learnt anything may spend its budget uniformly: then no map is drawn
    sm = res["results"][1].get("sample_map")
    assert sm is not None and len(maps) == int(np.ptp(sm["counts"]) > 0)


def test_clips_shorter_than_the_window_are_refused_with_the_fix(clip_store, tmp_path):
    from training.config import TrainConfig
    from training.errors import DataError
    from training.loop import train
    cfg = TrainConfig(model="temporal", model_cfg={**build("temporal").tiny, "frames": 5}, steps=1, batch=1,
                      crop=16, workers=0)
    with pytest.raises(DataError, match=r"longest is 4.*windows of 5 frames.*--model-cfg"):
        train(cfg, clip_store, tmp_path / "run", progress=False)
