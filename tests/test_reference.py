"""The reference (issue 47): shutter times by the frame's motion, a standard error from per-sample moments
inside each launch, and no banding.

The standard error is tested the way it is used: two references of one frame with independent render
seeds give per pixel ``z = (a - b) / sqrt(se_a^2 + se_b^2)``, which must look standard normal (standard
deviation within 0.85 to 1.15, fewer than 1% of |z| > 3), on a static and on a moving frame. Banding is
tested against a dense-time reference (256 shutter times) with the same z; a reference of one time fails
it, so the test can fail.
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from pipeline.bench_reference import z_scores            # where either has an error: the sky's pixels have none
from tests.test_render import ball_scene, cfg

REF = dict(ref_spp=1024, ref_passes=32, ref_min_passes=16, layer_levels=0, spp=2)


def normal_enough(z: np.ndarray) -> tuple[float, float]:
    return float(z.std()), float(np.mean(np.abs(z) > 3))


def reference(spec, **kw):
    """The reference of frame 0 of ``spec``, with its ``mi.render`` launches counted and its displacement."""
    from pipeline import render as R
    from pipeline.bench_reference import counted
    fs = R.FrameScene(spec, 0, cfg(**{**REF, **kw}))
    with counted(fs) as c:
        out = R.render_reference(fs)
    out["launches"], out["displacement"] = c["launches"], fs.displacement
    return out


def test_time_count_follows_the_rule():
    from pipeline.render import reference_time_count as T
    assert T(0.0, 1024, 16) == 1 and T(-1.0, 1024, 16) == 1
    assert T(math.inf, 1024, 16) == 16 and T(math.nan, 1024, 16) == 1       # NaN: no motion measured
    # T >= 3.52 d^(3/4) at 1024 samples, as a power of two
    assert [T(d, 1024, 64) for d in (0.05, 0.2, 0.5, 1.0, 2.0, 4.0, 8.0)] == [1, 2, 4, 4, 8, 16, 32]
    assert T(8.0, 1024, 16) == 16                                           # the cap
    assert T(1.0, 8, 16) <= T(1.0, 1024, 16)                                 # fewer samples, more noise to hide in
    for d in np.linspace(0.01, 20, 50):                                      # the criterion holds where not capped
        t = T(d, 1024, 1 << 20)
        assert d * math.sqrt(6 * max(d, 1) * 1024) / (12.649 * t * t) <= 0.5 + 1e-9


def test_displacement_bounds_the_motion_of_the_samples(mi):
    """The frame's shutter displacement bounds what its samples' own motion vectors say (they are one
    frame of velocity; the shutter is the whole frame here), and is 0 for a static frame."""
    from pipeline import render as R
    fs = R.FrameScene(ball_scene(motion=True), 0, cfg(spp=4, ref_spp=0, layer_levels=0))
    out = R.input_samples(fs)
    F = out["features"]
    from stores.contract import FEATURE_NAMES
    mx, my = FEATURE_NAMES.index("motion_x"), FEATURE_NAMES.index("motion_y")
    seen = float(np.hypot(F[..., mx], F[..., my]).max())
    assert 0.5 * fs.displacement < seen <= fs.displacement * 1.001
    assert R.FrameScene(ball_scene(), 0, cfg(ref_spp=0, layer_levels=0)).displacement == 0.0


@pytest.mark.parametrize("motion", [False, True], ids=["static", "moving"])
def test_two_references_agree_within_their_standard_errors(mi, motion):
    spec = ball_scene(motion=motion)
    a = reference(spec)
    b = reference(spec, seed_offset=1)
    assert a["reference"].tobytes() != b["reference"].tobytes()             # independent samples
    z = z_scores(a, b)
    assert z.size > 300
    std, tail = normal_enough(z)
    assert 0.85 <= std <= 1.15 and tail < 0.01, (std, tail)
    # launches: one for a static frame, one a shutter time for a moving one, at most 16
    assert a["ref_time_slices"] == (16 if motion else 1)
    assert a["launches"] == a["ref_time_slices"] and a["reference_spp"] == 1024


def test_no_banding_against_a_dense_time_reference(mi):
    spec = ball_scene(motion=True)
    dense = reference(spec, ref_passes=2, ref_min_passes=2, ref_times=256, seed_offset=3)
    assert dense["ref_time_slices"] == 256 and dense["launches"] == 256
    rule = reference(spec)
    std, tail = normal_enough(z_scores(rule, dense))
    assert 0.85 <= std <= 1.15 and tail < 0.01, (std, tail)
    # one time (no motion blur) fails the same test
    std, tail = normal_enough(z_scores(reference(spec, ref_times=1), dense))
    assert std > 1.15 or tail >= 0.01


def test_an_early_stop_takes_few_rounds(mi):
    """With a target the reference renders a first round of ref_min_passes passes, then what the measured
    error predicts: a few rounds of one launch a time, not one launch a pass."""
    out = reference(ball_scene(), ref_spp=4096, ref_passes=64, ref_target_rel_stderr=0.02)
    assert out["reference_rel_stderr"] <= 0.02 and out["reference_spp"] < 4096
    assert out["launches"] <= 3 and out["reference_spp"] % 64 == 0


def test_batch_means_renders_as_before(mi):
    """``reference: batch_means`` (what stores made before ``reference`` resume with) still renders passes of
    ``ref_time_slices`` times, one launch each."""
    out = reference(ball_scene(motion=True), ref_spp=256, ref_passes=16, reference="batch_means")
    assert out["launches"] == 16 * 4 and out["ref_time_slices"] == 64


def test_a_store_made_before_reference_existed_resumes_with_batch_means(tmp_path):
    from pipeline.dataset import check_existing_store
    from pipeline.config import load_config
    from stores.writer import open_or_create
    from tests.test_pipeline_safety import SMOKE
    cfg_ = load_config(SMOKE)
    old = json.loads(json.dumps(cfg_.with_overrides(render={**cfg_.render, "reference": "batch_means"}).content_dict()))
    for k in ("reference", "ref_max_times", "ref_times"):
        old["render"].pop(k)
    store = str(tmp_path / "old.zarr")
    open_or_create(store, cfg_.store_layout(), old)
    run_cfg = check_existing_store(cfg_, store)
    assert run_cfg.render_config().reference == "batch_means"
    # and once resumed (the store records its method), again
    open_or_create(store, cfg_.store_layout(), run_cfg.content_dict())
    assert check_existing_store(cfg_, store).render_config().reference == "batch_means"


def test_configs_naming_the_old_settings_still_load():
    from pipeline.config import DatasetConfig
    from pipeline.render import RenderConfig
    d = {"name": "x", "seed": 1, "resolution": [16, 16], "scenes": [{"kind": "indoor", "count": 1}],
         "render": {"ref_spp": 256, "ref_passes": 16, "ref_time_slices": 8}}
    rc = DatasetConfig.from_dict(d).render_config()
    assert (rc.reference, rc.ref_passes, rc.ref_time_slices) == ("moments", 16, 8)
    assert dataclasses.replace(rc, reference="batch_means").ref_time_slices == 8
    with pytest.raises(Exception, match="render.reference"):
        RenderConfig(reference="passes")
    with pytest.raises(Exception, match="render.ref_times"):
        RenderConfig(ref_spp=256, ref_passes=16, ref_times=16)                 # 8 samples a half pass


def test_layers_count_a_pixel_with_a_nan_sample_and_a_pixel_with_inf_alike(mi, monkeypatch):
    """A layer pixel whose samples held a NaN (the moment integrator's NaN share) and one whose mean is Inf
    are both counted in ``nonfinite_layers``, each once, and both stored finite."""
    from pipeline import render as R
    fs = R.FrameScene(ball_scene(), 0, cfg(**{**REF, "layer_levels": 1}))
    W, H = fs.cfg.res

    def fake(fs_, spp, stream, index, max_slices=None, *, integrator=None, channels=3):
        img = np.zeros((H, W, channels))
        img[0, 0, 6] = 0.5                      # half its samples were NaN
        img[1, 1, 0] = np.inf                   # an Inf mean
        img[2, 2, 6] = 0.25
        img[2, 2, 1] = np.inf                   # both: one pixel
        return img
    monkeypatch.setattr(R.layers, "render_sliced", fake)
    layers, bad = R.render_layers(fs)
    assert bad == 3 and np.isfinite(layers).all()
