"""What a kernel-predicting model may spread (training.models.robust): on a constructed firefly (one value
of 1e8 in a frame of 0.1) and a constructed sun (a 1e6 pixel in a sky of 1), every model that bounds its
filter input keeps every output pixel within a small multiple of the neighbourhood's level, where the
unbounded model (``outliers: 0``, its form before) spreads the value over its kernel; an old checkpoint
without the setting builds unbounded, as it was trained."""
from __future__ import annotations

import pytest
import torch

from training.models import build, get, names
from training.models.robust import OUTLIER_FLOOR, bound_outliers, neighbourhood_level

BOUNDED = [n for n in names() if get(n).outlier_bound > 0 and get(n).__module__.startswith("training.models.")]
H = W = 24


def _batch(name: str, value: float, background: float, every_sample: bool = False) -> dict:
    """An example batch of the model's kind with every radiance ``background`` but one value at (12, 12):
    every sample of the pixel for a per-pixel model, one sample of it (``every_sample``: all) for a
    per-sample model."""
    m = build(name, **get(name).tiny)
    spec = m.input_spec()
    spp = spec.default_spp if spec.kind != "sampled-layers" else 4
    b = spec.input_kind.example_batch(1, spp, H, W, spec.frames, torch.Generator().manual_seed(1))
    rad = torch.full_like(b["radiance"], background)
    first = slice(None) if every_sample else 0
    if rad.dim() == 6:                                  # B T S 3 H W: the last frame's first sample
        rad[:, -1, first, :, 12, 12] = value
    elif rad.dim() == 5 and spec.kind in ("samples", "clips"):
        rad[:, first, :, 12, 12] = value                # B S 3 H W: one sample
    else:
        rad[..., 12, 12] = value                        # B 3 H W or B T 3 H W: the pixel
    b["radiance"] = rad
    if "albedo" in b:
        b["albedo"] = torch.full_like(b["albedo"], 0.5)
    return b


def _out(name: str, outliers: float, batch: dict) -> torch.Tensor:
    torch.manual_seed(0)
    m = build(name, **{**get(name).tiny, "outliers": outliers}).eval()
    with torch.no_grad():
        return m(batch)


@pytest.mark.parametrize("name", BOUNDED)
def test_a_firefly_is_not_spread(name):
    batch = _batch(name, 1e8, 0.1)
    bounded, before = _out(name, get(name).outlier_bound, batch), _out(name, 0.0, batch)
    assert torch.isfinite(bounded).all()
    assert bounded.max() < 1e3, f"{name}: {float(bounded.max()):.4g}"      # a few times 64 x 0.1 + 1
    assert before.max() > 1e4                                              # unbounded: 1e8 over its kernel


@pytest.mark.parametrize("name", BOUNDED)
def test_the_sun_is_not_spread_over_its_sky(name):
    batch = _batch(name, 1e6, 1.0, every_sample=True)
    out = _out(name, get(name).outlier_bound, batch)
    sky = torch.ones(H, W, dtype=torch.bool)
    sky[12, 12] = False                                 # every pixel but the sun's
    assert out[..., sky].max() < 1e3 < _out(name, 0.0, batch)[..., sky].max()


def test_the_bound_is_the_neighbourhoods_level():
    lum = torch.full((1, 1, 9, 9), 0.5)
    lum[0, 0, 4, 4] = 1e6
    level = neighbourhood_level(lum)
    assert level[0, 0, 4, 4] == pytest.approx(0.5, rel=1e-5)             # its own value is left out
    assert level[0, 0, 0, 0] == pytest.approx(0.5, rel=1e-5)             # corners: the window in the frame
    rad = torch.full((1, 3, 9, 9), 0.5)
    rad[0, :, 4, 4] = torch.tensor([2e6, 1e6, 0.0])
    out = bound_outliers(rad, 16.0)
    lum_out = (out[0, :, 4, 4] * torch.tensor([0.2126, 0.7152, 0.0722])).sum()
    assert lum_out == pytest.approx(16 * 0.5 + OUTLIER_FLOOR, rel=1e-5)    # cut to the bound ...
    assert out[0, 0, 4, 4] / out[0, 1, 4, 4] == pytest.approx(2.0)        # ... its hue kept
    assert torch.equal(out[..., :4, :], rad[..., :4, :]) and torch.equal(bound_outliers(rad, 0.0), rad)


def test_an_old_checkpoint_builds_and_resumes_as_it_was_trained(tmp_path):
    """A checkpoint without the settings ``outliers`` and ``albedo_offset`` (written before they existed)
    builds with the values it was trained with, and a run resumed from it trains that model on."""
    from test_training import make_store
    from training import checkpoint as ckpt
    from training.config import TrainConfig
    from training.loop import train
    from training.models._pixel import DEMOD_EPS
    m = build("nbg", **get("nbg").tiny)
    old = {k: v for k, v in m.config.items() if k not in ("outliers", "albedo_offset")}
    ck = {"model": "nbg", "model_config": old, "state_dict": m.state_dict()}
    built = ckpt.build_model(ck)
    assert (built.outliers, built.albedo_offset) == (0.0, DEMOD_EPS)
    assert ckpt.build_model({**ck, "model_config": m.config}).outliers == get("nbg").outlier_bound > 0
    store = make_store(tmp_path / "s.zarr", h=16, w=16, per_split=(2, 1, 1))
    cfg = TrainConfig.from_dict({"model": "nbg", "steps": 2, "batch": 1, "crop": 16, "val_every": 0, "workers": 0,
                                 "model_cfg": dict(get("nbg").tiny)})
    train(cfg, store, tmp_path / "run", progress=False, stop_after=1)
    saved = ckpt.load(tmp_path / "run" / "checkpoint.pt")
    saved["model_config"] = {k: v for k, v in saved["model_config"].items() if k not in ("outliers", "albedo_offset")}
    torch.save(saved, tmp_path / "run" / "checkpoint.pt")             # as a run begun before the settings
    train(cfg, store, tmp_path / "run", progress=False)
    resumed = ckpt.load(tmp_path / "run" / "checkpoint.pt")
    assert resumed["step"] == 2 and resumed["model_config"]["outliers"] == 0.0
    assert resumed["model_config"]["albedo_offset"] == DEMOD_EPS


@pytest.mark.parametrize("name", ["nbg", "wskpn"])
def test_a_black_albedo_neighbour_is_not_amplified(name):
    """Black metal (albedo 0, radiance 1) beside white diffuse (albedo 0.8, radiance 0.1): what the filter
    carries across is multiplied by (0.8 + offset) / offset, 81 with the papers' 0.01 (up to 40 here) and
    9 with the models' 0.1."""
    from training.models._pixel import ALBEDO_OFFSET, DEMOD_EPS
    outs = {}
    for off in (DEMOD_EPS, ALBEDO_OFFSET):
        torch.manual_seed(0)
        m = build(name, **{**get(name).tiny, "albedo_offset": off}).eval()
        spec = m.input_spec()
        b = spec.input_kind.example_batch(1, 1, H, W, 1, torch.Generator().manual_seed(1))
        b["radiance"] = torch.full_like(b["radiance"], 0.1)
        b["radiance"][..., :12] = 1.0
        b["albedo"] = torch.full_like(b["albedo"], 0.8)
        b["albedo"][..., :12] = 0.0
        with torch.no_grad():
            outs[off] = m(b)[..., 12:].max()
    assert outs[ALBEDO_OFFSET] < (0.8 + ALBEDO_OFFSET) / ALBEDO_OFFSET < outs[DEMOD_EPS]
    assert get(name).legacy_config["albedo_offset"] == DEMOD_EPS            # old checkpoints: as trained


@pytest.mark.parametrize("name", ["nbg", "wskpn"])
def test_a_light_seen_directly_keeps_its_energy_and_a_firefly_is_still_cut(name):
    """A 3x3 lamp of 8000 in a frame of 0.1 (the real-scene suite's metals: a light seen directly) keeps its
    energy at its own pixels, unspread (``keep_lights``, the default); without it the bound drops it (what
    took the image's mean to 26-29% there). A one-pixel firefly of the same value is still cut either way."""
    from training.models.robust import light_excess
    outs = {}
    for keep in (True, False):
        torch.manual_seed(0)
        m = build(name, **{**get(name).tiny, "keep_lights": keep}).eval()
        b = m.input_spec().input_kind.example_batch(1, 1, H, W, 1, torch.Generator().manual_seed(1))
        b["albedo"] = torch.full_like(b["albedo"], 0.5)
        lamp, fly = torch.full_like(b["radiance"], 0.1), torch.full_like(b["radiance"], 0.1)
        lamp[..., 11:14, 11:14] = 8000.0
        fly[..., 12, 12] = 8000.0
        with torch.no_grad():
            outs[keep] = (m({**b, "radiance": lamp}), m({**b, "radiance": fly}))
    lamp_in = 9 * 3 * 8000.0
    kept, dropped = outs[True][0].sum(), outs[False][0].sum()
    assert abs(float(kept) / lamp_in - 1) < 0.02 and float(dropped) < 0.1 * lamp_in
    ring = outs[True][0].clone()
    ring[..., 11:14, 11:14] = 0
    assert float(ring.max()) < 0.1 * 8000                       # not spread around the lamp
    assert float(outs[True][1].max()) < 0.1 * 8000 and float(outs[False][1].max()) < 0.1 * 8000     # the firefly: cut
    # the rule itself: a cut pixel with two cut neighbours is a light, an isolated one is not
    x = torch.zeros(1, 3, 8, 8)
    x[..., 2, 2] = 1.0
    x[..., 5, 4:7] = 1.0
    e = light_excess(x, torch.zeros_like(x))
    assert e[..., 2, 2].sum() == 0 and e[..., 5, 5].sum() == 3 and e[..., 5, 4].sum() == 0
    assert get(name).legacy_config["keep_lights"] is False                    # old checkpoints: as trained
