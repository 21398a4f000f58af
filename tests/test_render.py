"""pipeline.render on tiny hand-written scenes: contract, unbiasedness against mi.render, features, seeds.

Statistics: estimates are compared with an independent oracle (Mitsuba's own ``mi.render`` at high
spp of a scene built by ``scene_gen.to_mitsuba``) through z-scores of image means and of 4x4-block
means, with variances from the per-sample variance of the input loop (not fudge factors).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from scene_gen.spec import (CameraSpec, LightSpec, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, TextureSpec,
                            Transform)
from stores.contract import FEATURE_GROUPS, FRAME_META
from tests.render_probe import camera_depth, expected_shapes, shape_index, trace

G = FEATURE_GROUPS
RES = (24, 16)
# The floor's specular colour as its BSDF renders it: roughplastic's F0 at normal incidence for int_ior 1.5
# against Mitsuba's default exterior, air (1.000277), whatever the spec's own specular_color field says.
PLASTIC_F0 = ((1.5 / 1.000277 - 1.0) / (1.5 / 1.000277 + 1.0)) ** 2


def ball_scene(*, defocus=False, motion=False, frames=1, seed=7, cam_step=(0.0, 0.0, 0.0), light=None,
               extra=()):
    """A red diffuse sphere on a green rough-plastic floor under a constant environment."""
    cams = tuple(CameraSpec(origin=(cam_step[0] * f, 1.0 + cam_step[1] * f, 5.0 + cam_step[2] * f), target=(0.0, -0.2, 0.0),
                            fov=40.0, aperture_radius=0.25 if defocus else 0.0, focus_distance=5.0)
                 for f in range(frames))
    objs = (ObjectSpec("ball", MeshSpec("sphere"), MaterialSpec("diffuse", base_color=(0.8, 0.3, 0.2)),
                       velocity=(0.6, 0.0, 0.0) if motion else None),
            ObjectSpec("floor", MeshSpec("plane"),
                       MaterialSpec("roughplastic", base_color=(0.2, 0.6, 0.3), specular_color=(0.5, 0.4, 0.3),
                                    roughness=0.3),
                       transform=Transform(translate=(0.0, -1.0, 0.0), scale=(6.0, 1.0, 6.0)))) + tuple(extra)
    lights = (light or LightSpec("constant", {"radiance": (1.0, 1.0, 1.0)}),)
    return SceneSpec("outdoor", seed, objs, lights, cams, shutter=1.0)


def top_down_scene(distance=3.0, *, aperture=0.0, focus=3.0):
    """A pinhole/thin-lens camera looking straight down at a huge diffuse floor at y = 0."""
    cam = CameraSpec(origin=(0.0, distance, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, -1.0), fov=50.0,
                     aperture_radius=aperture, focus_distance=focus)
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse", base_color=(0.25, 0.5, 0.75)),
                       transform=Transform(scale=(100.0, 1.0, 100.0)))
    return SceneSpec("indoor", 3, (floor,), (LightSpec("constant", {"radiance": (1.0, 1.0, 1.0)}),), (cam,))


def cfg(**kw):
    from pipeline.render import RenderConfig
    base = dict(res=RES, spp=8, ref_spp=256, ref_passes=16, layer_levels=6)
    base.update(kw)
    return RenderConfig(**base)


def oracle(mi, spec, frame, spp, seed, taus=None, res=RES, with_var=False, passes=8):
    """Plain mi.render of a freshly built scene (float64 HWC), averaged over scene times ``taus``.

    ``with_var``: also the per-sample variance (HWC) at those times, from ``passes`` independent
    passes per time (the variance of a time-sliced mean of n samples is its mean over times / n).
    """
    from scene_gen import to_mitsuba
    taus = [None] if taus is None else list(taus)
    acc, var = 0.0, 0.0
    for i, tau in enumerate(taus):
        scene = to_mitsuba.load(spec, frame, res, tau=tau)
        if not with_var:
            acc = acc + np.asarray(mi.render(scene, spp=spp, seed=seed + 7919 * i), np.float64)[..., :3]
            continue
        runs = np.stack([np.asarray(mi.render(scene, spp=spp // passes, seed=seed + 7919 * i + 31 * j),
                                    np.float64)[..., :3] for j in range(passes)])
        acc = acc + runs.mean(0)
        var = var + runs.var(0, ddof=1) * (spp // passes)
    return (acc / len(taus), var / len(taus)) if with_var else acc / len(taus)


def blocks(a, b=4):
    h, w = a.shape[:2]
    return a[: h // b * b, : w // b * b].reshape(h // b, b, w // b, b, -1).mean(axis=(1, 3))


def zmax(est, var_est, ora, var_ora):
    """Max |z| of image means and of 4x4 block means (per channel); pixel variances of the means."""
    zs = []
    for agg, npx in ((lambda a: a.reshape(-1, a.shape[-1]).mean(0, keepdims=True), est.shape[0] * est.shape[1]),
                     (blocks, 16)):
        d = agg(est) - agg(ora)
        v = (agg(var_est) + agg(var_ora)) / npx
        zs.append(np.abs(d) / np.sqrt(v + 1e-30))
    return float(max(z.max() for z in zs))


def pixel_sample_var(radiance):
    """Per-pixel variance of one sample (HWC) from per-sample radiance (HWSC)."""
    return radiance.astype(np.float64).var(axis=2, ddof=1)


# -------------------------------------------------------------------------------------------------
def test_config_validation():
    from pipeline.errors import ConfigError
    from pipeline.render import RenderConfig
    c = RenderConfig(res=32)
    assert c.res == (32, 32) and RenderConfig.from_dict(c.to_dict()) == c
    for bad, word in [(dict(spp=0), "spp"), (dict(ref_spp=100, ref_passes=32), "ref_spp"),
                      (dict(res=(0, 4)), "res"), (dict(ref_target_rel_stderr=-1.0), "ref_target_rel_stderr"),
                      (dict(time_slices=0), "time_slices"), (dict(max_value=float("inf")), "max_value"),
                      (dict(ref_min_passes=64, ref_passes=32), "ref_min_passes")]:
        with pytest.raises(ConfigError, match=word):
            RenderConfig(**bad)
    with pytest.raises(ConfigError, match="unknown"):
        RenderConfig.from_dict({"spp": 8, "sppp": 2})


def test_stream_seeds_distinct():
    from pipeline.render import (STREAM_INPUTS, STREAM_LAYER, STREAM_ORACLE, STREAM_REFERENCE, stream_seed)
    seeds = [stream_seed(7, 0, STREAM_INPUTS, k, c) for k in range(4) for c in range(4)]
    seeds += [stream_seed(7, 0, STREAM_LAYER, n, k) for n in range(6) for k in range(4)]
    seeds += [stream_seed(7, 0, STREAM_REFERENCE, p) for p in range(64)]
    seeds += [stream_seed(7, 0, STREAM_ORACLE, 0, k) for k in range(16)]
    seeds += [stream_seed(7, 1, STREAM_INPUTS, 0, 0), stream_seed(8, 0, STREAM_INPUTS, 0, 0)]
    assert len(set(seeds)) == len(seeds)
    assert all(0 <= s < 2 ** 31 for s in seeds)
    assert stream_seed(7, 0, STREAM_INPUTS, 0, 0) == stream_seed(7, 0, STREAM_INPUTS, 0, 0)


@pytest.fixture(scope="module")
def static_frame(mi):
    from pipeline.render import render_frame
    spec = ball_scene()
    return spec, render_frame(spec, 0, cfg(spp=32, oracle_spp=64))


def test_contract_shapes_and_meta(static_frame):
    spec, out = static_frame
    for name, (shape, dtype) in expected_shapes(cfg(spp=32)).items():
        assert out[name].shape == shape, name
        assert out[name].dtype == np.dtype(dtype), name
        assert np.isfinite(out[name]).all(), name
    meta = out["meta"]
    assert set(meta) == set(FRAME_META)
    for k, typ in FRAME_META.items():
        assert isinstance(meta[k], typ), k
    assert SceneSpec.from_json(meta["scene_json"]) == spec
    assert meta["reference_spp"] == 256 and not meta["has_motion"] and not meta["has_defocus"]
    assert meta["nonfinite_inputs"] == meta["nonfinite_layers"] == meta["nonfinite_reference"] == 0
    f = out["features"]
    assert np.all(f[..., G["motion"]] == 0) and np.all(f[..., G["time"]] == 0)
    assert np.all(f[..., G["lens"]] == 0) and np.all(f[..., G["coc"]] == 0)
    # guides are the per-pixel sample means
    np.testing.assert_allclose(out["guides_depth"][..., 0], f[..., 3].mean(axis=2), rtol=1e-6)


def _check_unbiased(mi, spec, out, cfg_, layer_taus=None, input_taus=None, ref_taus=None, ora_spp=2048):
    """Inputs, each layer, all layers together and the reference agree with mi.render (z < 4.5)."""
    var1 = pixel_sample_var(out["radiance"])
    S = out["radiance"].shape[2]
    ora = oracle(mi, spec, 0, ora_spp, 99991, input_taus)
    assert zmax(out["radiance"].mean(axis=2), var1 / S, ora, var1 / ora_spp) < 4.5
    allsum = 0.0
    for lvl in range(cfg_.layer_levels):
        n = 2 ** lvl
        ora_l, var_l = ora, var1
        if layer_taus is not None:  # condition on the layer's slice times; variance at those times
            ora_l, var_l = oracle(mi, spec, 0, ora_spp, 50021 + lvl, layer_taus[lvl], with_var=True)
        assert zmax(out["layers"][lvl], var_l / n, ora_l, var_l / ora_spp) < 4.5, f"layer {lvl}"
        allsum = allsum + out["layers"][lvl] * n
    if layer_taus is None:
        total = 2 ** cfg_.layer_levels - 1
        assert zmax(allsum / total, var1 / total, ora, var1 / ora_spp) < 4.5
    ora_r = ora if ref_taus is None else oracle(mi, spec, 0, ora_spp // len(ref_taus) * 4, 777, ref_taus)
    se2 = out["reference_stderr"].astype(np.float64) ** 2
    assert zmax(out["reference"], se2, ora_r, var1 / ora_spp) < 4.5
    if ref_taus is not None:
        return  # with motion the batch means also hold the variance over pass times
    # the standard error is honest: on average it matches the input loop's per-sample variance
    ratio = se2.sum() / (var1 / out["meta"]["reference_spp"]).sum()
    assert 0.5 < ratio < 2.0, ratio


def test_unbiased_static(mi, static_frame):
    spec, out = static_frame
    _check_unbiased(mi, spec, out, cfg(spp=32))
    # the oracle image of the frame (a plain mi.render) agrees as well
    var1 = pixel_sample_var(out["radiance"])
    assert zmax(out["oracle"], var1 / 64, out["reference"], out["reference_stderr"] ** 2.0) < 4.5


def test_unbiased_defocus(mi):
    from pipeline.render import render_frame
    spec = ball_scene(defocus=True)
    c = cfg(spp=32)
    out = render_frame(spec, 0, c)
    assert out["meta"]["has_defocus"]
    _check_unbiased(mi, spec, out, c)


def test_unbiased_motion(mi):
    from pipeline import render as R
    from pipeline.render.settings import time_rng
    spec = ball_scene(motion=True)
    c = cfg(spp=32, time_slices=2, ref_time_slices=2)
    out = R.render_frame(spec, 0, c)
    assert out["meta"]["has_motion"]
    t = out["features"][..., G["time"]][..., 0]
    slices = math.gcd(c.time_slices, c.spp)
    tk = np.unique(t)
    assert len(tk) == slices
    # stratified: slice k's time lies in [k/g, (k+1)/g) and samples are ordered by slice
    assert np.all((tk >= np.arange(slices) / slices) & (tk < (np.arange(slices) + 1) / slices))
    assert np.all(t[..., :c.spp // slices] == tk[0])
    layer_taus = []
    for lvl in range(c.layer_levels):
        g = math.gcd(c.time_slices, 2 ** lvl)
        layer_taus.append(spec.shutter * R.slice_times(time_rng(spec.seed, 0, c, R.STREAM_LAYER, lvl), g))
    ref_taus = (np.arange(8) + 0.5) / 8 * spec.shutter
    _check_unbiased(mi, spec, out, c, layer_taus=layer_taus, input_taus=spec.shutter * tk, ref_taus=ref_taus)
    # the blur is real: the motion-blurred reference differs from the frame at rest
    still = oracle(mi, spec, 0, 256, 5)
    assert np.abs(out["reference"] - still).max() > 0.1


def merged_ball_scene(**kw):
    """ball_scene plus static boxes sharing the floor's and the ball's materials (merged by the renderer)."""
    base = ball_scene()
    ball, floor = base.objects
    extra = (ObjectSpec("box_a", MeshSpec("box"), floor.material, Transform((-1.2, -0.7, 0.5), scale=(0.3, 0.3, 0.3))),
             ObjectSpec("box_b", MeshSpec("box"), floor.material, Transform((1.3, -0.7, -0.5), scale=(0.3, 0.3, 0.3))),
             ObjectSpec("box_c", MeshSpec("box"), ball.material, Transform((0.9, -0.8, 1.0), scale=(0.2, 0.2, 0.2))))
    return ball_scene(extra=extra, **kw)


def test_unbiased_and_features_with_merged_shapes(mi):
    """Static objects sharing a material are merged (fewer shapes), yet the estimates agree with
    mi.render on the unmerged scene and every sample keeps its object's specular colour and roughness."""
    from pipeline.render import FrameScene, render_frame
    from scene_gen.to_mitsuba import MERGED_PREFIX
    spec = merged_ball_scene(motion=True)
    c = cfg(spp=32, time_slices=1, ref_time_slices=1)
    fs = FrameScene(spec, 0, c)
    ids = [s.id() for s in fs.scene.shapes()]
    assert len(ids) < len(spec.objects) and any(i.startswith(MERGED_PREFIX) for i in ids) and "ball" in ids
    static = dataclasses.replace(spec, shutter=0.0)
    out = render_frame(static, 0, c)
    _check_unbiased(mi, static, out, c)
    f = out["features"]
    alb = f[..., G["albedo"]]
    floor_like = np.all(np.abs(alb - [0.2, 0.6, 0.3]) < 1e-4, axis=-1)     # floor and boxes a, b
    ball_like = np.all(np.abs(alb - [0.8, 0.3, 0.2]) < 1e-4, axis=-1)      # ball and box c
    assert floor_like.sum() > 100 and ball_like.sum() > 100
    np.testing.assert_allclose(f[floor_like][:, G["specular"]], PLASTIC_F0, atol=1e-6)
    np.testing.assert_allclose(f[floor_like][:, G["roughness"]], 0.3, atol=1e-6)
    np.testing.assert_allclose(f[ball_like][:, G["roughness"]], 1.0)
    # the moving ball keeps its own shape and velocity: its samples have motion, the merged boxes none
    mv = render_frame(spec, 0, dataclasses.replace(c, ref_spp=0, layer_levels=0))["features"]
    ball = np.all(np.abs(mv[..., G["albedo"]] - [0.8, 0.3, 0.2]) < 1e-4, axis=-1)
    assert np.abs(mv[ball][:, G["motion"]]).max() > 0.1


def test_features_top_down_depth_normal_albedo(mi):
    """Depth equals the analytic ray cast D / cos(theta) for every sample (within its pixel's range)."""
    from pipeline.render import render_frame
    D = 3.0
    spec = top_down_scene(D)
    out = render_frame(spec, 0, cfg(res=(16, 12), ref_spp=0, layer_levels=0))
    f = out["features"]
    W, H = 16, 12
    tx = math.tan(math.radians(25.0))
    ty = tx * H / W
    x0 = (np.arange(W) / W * 2 - 1) * tx
    x1 = ((np.arange(W) + 1) / W * 2 - 1) * tx
    y0 = (1 - (np.arange(H) + 1) / H * 2) * ty
    y1 = (1 - np.arange(H) / H * 2) * ty
    X0, Y0 = np.meshgrid(x0, y0)
    X1, Y1 = np.meshgrid(x1, y1)
    near2 = np.clip(0, X0, X1) ** 2 + np.clip(0, Y0, Y1) ** 2
    far2 = np.maximum(X0 ** 2, X1 ** 2) + np.maximum(Y0 ** 2, Y1 ** 2)
    depth = f[..., 3]
    # 1e-3: Mitsuba's float32 sample-to-camera transform bends rays (~1e-4 relative)
    # the depth range inside one pixel is 0.5-5 %
    assert np.all(depth >= D * np.sqrt(1 + near2)[..., None] * (1 - 1e-3))
    assert np.all(depth <= D * np.sqrt(1 + far2)[..., None] * (1 + 1e-3))
    assert depth.max() > D * 1.12 and depth.min() < D * 1.01
    np.testing.assert_allclose(f[..., G["normal"]], np.broadcast_to([0, 1, 0], f.shape[:3] + (3,)), atol=1e-5)
    np.testing.assert_allclose(f[..., G["albedo"]], np.broadcast_to([0.25, 0.5, 0.75], f.shape[:3] + (3,)), atol=1e-5)
    assert np.all(f[..., G["specular"]] == 0.0) and np.all(f[..., G["roughness"]] == 1.0)      # diffuse


def test_features_ball(static_frame):
    spec, out = static_frame
    f = out["features"]
    hit = f[..., 3] > 0
    assert 0.2 < hit.mean() < 1.0
    n = np.linalg.norm(f[..., G["normal"]], axis=-1)
    np.testing.assert_allclose(n[hit], 1.0, atol=1e-4)
    assert np.all(n[~hit] == 0)
    alb = f[..., G["albedo"]]
    assert alb.min() >= 0 and alb.max() <= 1
    # per-shape table: samples with the floor's albedo carry the floor BSDF's specular colour and roughness
    floor = np.all(np.abs(alb - [0.2, 0.6, 0.3]) < 1e-4, axis=-1)
    ball = np.all(np.abs(alb - [0.8, 0.3, 0.2]) < 1e-4, axis=-1)
    assert floor.sum() > 100 and ball.sum() > 100
    np.testing.assert_allclose(f[floor][:, G["specular"]], PLASTIC_F0, atol=1e-6)
    np.testing.assert_allclose(f[floor][:, 10], 0.3, atol=1e-6)
    np.testing.assert_allclose(f[ball][:, 10], 1.0)
    np.testing.assert_allclose(f[ball][:, G["specular"]], 0.0)          # a diffuse BSDF has no specular lobe


def test_lens_uniform_and_coc(mi):
    """Lens samples are uniform on the unit disk; CoC is 0 at the focus distance and obeys the thin lens."""
    from scipy import stats

    from scene_gen import projection as C
    from pipeline import render as R
    c = cfg(res=(16, 12), spp=16, ref_spp=0, layer_levels=0)
    # plane exactly at the focus distance: CoC 0 everywhere on it
    out = R.render_frame(top_down_scene(3.0, aperture=0.3, focus=3.0), 0, c)
    f = out["features"]
    assert np.abs(f[..., 13]).max() < 1e-3
    lens = f[..., G["lens"]].reshape(-1, 2).astype(np.float64)
    r2 = (lens ** 2).sum(1)
    assert r2.max() <= 1 + 1e-6
    assert stats.kstest(r2, "uniform").pvalue > 1e-4
    assert stats.kstest((np.arctan2(lens[:, 1], lens[:, 0]) + np.pi) / (2 * np.pi), "uniform").pvalue > 1e-4
    # plane behind focus: positive CoC; the film position and the pinhole projection of the hit differ
    # by exactly -coc * lens (the thin-lens geometry, checked against Mitsuba's own rays)
    spec = top_down_scene(4.0, aperture=0.3, focus=2.5)
    fs = R.FrameScene(spec, 0, c)
    tr = trace(fs, 1234, 0, 12, 4, 0.0, debug=True)
    feats = tr["F"]
    coc = feats[:, 13]
    z = 4.0
    expect = 0.3 * (z - 2.5) / z * 16 / (2 * 2.5 * math.tan(math.radians(25)))
    np.testing.assert_allclose(coc, expect, rtol=1e-4)
    film_px = tr["film"] * np.array([16, 12])
    pin_px = C.project_pixels(fs.world_to_clip, tr["p"], (16, 12))
    np.testing.assert_allclose(film_px - pin_px, -coc[:, None] * feats[:, 14:16], atol=2e-3)
    # in front of the focus plane: negative
    fs2 = R.FrameScene(top_down_scene(2.0, aperture=0.3, focus=2.5), 0, c)
    feats2 = trace(fs2, 99, 0, 12, 4, 0.0)["F"]
    assert np.all(feats2[:, 13] < 0)


def test_motion_vectors_reproject(mi):
    """Per sample: a ray from the previous frame's camera through p + motion hits the same surface point
    (moved back by one frame's velocity), checked with Mitsuba's own camera and ray cast."""
    from pipeline import render as R
    from scene_gen import projection as C
    from scene_gen import to_mitsuba
    spec = ball_scene(motion=True, frames=2, cam_step=(0.3, 0.1, -0.2))
    c = cfg(spp=4, ref_spp=0, layer_levels=0, time_slices=1)
    fs = R.FrameScene(spec, 1, c)
    t = 0.4
    fs.set_time(t)
    tr = trace(fs, 4321, 0, RES[1], 4, t, debug=True)
    feats = tr["F"].astype(np.float64)
    hit = tr["hit"].astype(bool)
    cur = C.project_pixels(fs.world_to_clip, tr["p"], RES)
    prev_px = cur + feats[:, 11:13]
    prev_scene = to_mitsuba.load(spec, 0, RES, tau=float(fs.tau(t)) - 1.0)
    sensor = prev_scene.sensors()[0]
    inside = np.all((prev_px > 0.5) & (prev_px < np.array(RES) - 0.5), axis=1) & hit
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((prev_px / np.array(RES)).T.astype(np.float32)), mi.Point2f(0.5, 0.5))
    si = prev_scene.ray_intersect(ray)
    p_prev = np.asarray(si.p).T
    idx = shape_index(fs, tr["sid"])
    expect = tr["p"] - fs.velocity[idx]
    err = np.linalg.norm(p_prev - expect, axis=1)
    # most agree to float precision; the others are occluded in the previous frame (the ray hits
    # something nearer to the previous camera) or graze the tessellated sphere's silhouette
    ok = inside & (err < 1e-3)
    assert inside.sum() > 300 and ok.sum() > 0.85 * inside.sum(), ok.sum() / inside.sum()
    o_prev = np.asarray(ray.o).T
    t_prev = np.asarray(si.t)
    occluded = t_prev < np.linalg.norm(expect - o_prev, axis=1) - 1e-3
    assert np.all((occluded | (err < 0.1))[inside & ~ok])
    moving = inside & (idx == idx[inside][np.argmax(np.linalg.norm(fs.velocity[idx[inside]], axis=1))])
    assert moving.sum() > 20 and np.abs(feats[moving, 11]).mean() > 0.5


def _features_oracle(fs, tr: dict, t: float) -> np.ndarray:
    """The 17 features (float64, N×17) from a debug trace's raw fields, in numpy float64 with
    ``scene_gen.projection``'s projection and circle of confusion: an independent form of the renderer's
    drjit feature kernel (which computes them in float32, in the trace's own kernel)."""
    from scene_gen import projection as C
    from pipeline.render import MOTION_LIMIT
    W, H = fs.cfg.res
    hit = tr["hit"].astype(bool)
    f = np.zeros((len(hit), 17))
    f[:, G["normal"]] = np.where(hit[:, None], tr["n"], 0.0)
    cos_view = np.abs(tr["d"].astype(np.float64) @ fs.view_axis)
    f[:, G["depth"]] = np.where(hit, tr["t"] + C.NEAR / np.maximum(cos_view, 1e-6), 0.0)[:, None]
    f[:, G["albedo"]] = np.clip(np.where(hit[:, None], tr["albedo"], 0.0), 0.0, 1.0)
    idx = np.where(hit, shape_index(fs, tr["sid"]), 0)
    f[:, G["specular"]] = fs.specular[idx]
    f[:, G["roughness"]] = fs.roughness[idx][:, None]
    pts = np.where(hit[:, None], tr["p"], tr["d"]).astype(np.float64)
    w = hit.astype(np.float64)
    cur = C.project_pixels(fs.world_to_clip, pts, fs.cfg.res, w)
    prev = C.project_pixels(fs.prev_world_to_clip, pts - fs.velocity[idx] * w[:, None], fs.cfg.res, w)
    mv = prev - cur
    lim = MOTION_LIMIT * max(W, H)
    f[:, G["motion"]] = np.clip(np.where(np.isfinite(mv), mv, 0.0), -lim, lim)
    if fs.has_defocus:
        z = np.where(hit, camera_depth(fs.cam, tr["p"]), np.inf)
        f[:, G["coc"]] = C.coc_pixels(fs.cam, z, W)[:, None]
        f[:, G["lens"]] = tr["lens"]
    f[:, G["time"]] = t if fs.has_motion else 0.0
    return f


@pytest.mark.parametrize("kind", ["motion+defocus", "static"])
def test_feature_kernel_matches_numpy_oracle(mi, kind):
    """The features computed inside the drjit trace kernel (float32) equal the float64 numpy form of
    every rule, per sample, on a moving camera and moving ball seen through a thin lens (frame 1 of a
    clip) and on a still; stills without motion get exactly zero motion vectors."""
    from pipeline import render as R
    if kind == "static":
        spec, frame, t = merged_ball_scene(), 0, 0.0
    else:
        spec, frame, t = ball_scene(motion=True, defocus=True, frames=2, cam_step=(0.3, 0.1, -0.2)), 1, 0.6
    fs = R.FrameScene(spec, frame, cfg(spp=4, ref_spp=0, layer_levels=0, time_slices=1))
    fs.set_time(t)
    tr = trace(fs, 777, 0, RES[1], 4, t, debug=True)
    got, want = tr["F"].astype(np.float64), _features_oracle(fs, tr, t)
    assert got.shape == want.shape == (RES[0] * RES[1] * 4, 17) and tr["F"].dtype == np.float32
    hit = tr["hit"].astype(bool)
    assert 0.2 < hit.mean() < 1.0
    for name, sl in G.items():
        scale = max(1.0, np.abs(want[:, sl]).max())
        np.testing.assert_allclose(got[:, sl], want[:, sl], rtol=0, atol=2e-5 * scale if name != "motion" else 2e-3,
                                   err_msg=name)
    if kind == "static":
        assert np.all(got[:, G["motion"]] == 0) and np.all(got[:, G["time"]] == 0) and np.all(got[:, G["coc"]] == 0)
    else:
        assert np.abs(got[:, G["motion"]]).max() > 1.0 and np.abs(got[:, G["coc"]]).max() > 0.1
        assert np.all(got[:, G["time"]] == np.float32(t))


def _warp(img0, m, alpha=1.0):
    """Bilinear lookup of img0 (HWC) at pixel + alpha * motion (HW2); returns (inside mask, warped)."""
    H, W = img0.shape[:2]
    yy, xx = np.mgrid[0:H, 0:W]
    sx, sy = xx + alpha * m[..., 0], yy + alpha * m[..., 1]
    x0, y0 = np.floor(sx).astype(int), np.floor(sy).astype(int)
    ax, ay = (sx - x0)[..., None], (sy - y0)[..., None]
    ok = (x0 >= 0) & (y0 >= 0) & (x0 < W - 1) & (y0 < H - 1)
    x0, y0 = np.clip(x0, 0, W - 2), np.clip(y0, 0, H - 2)
    return ok, ((1 - ax) * (1 - ay) * img0[y0, x0] + ax * (1 - ay) * img0[y0, x0 + 1]
                + (1 - ax) * ay * img0[y0 + 1, x0] + ax * ay * img0[y0 + 1, x0 + 1])


def test_clip_warp_matches_next_frame(mi):
    """Warping frame t-1 by frame t's motion vectors reproduces frame t on static diffuse unoccluded
    pixels (a checkered floor seen from a moving camera), and the error is smallest at the vectors' scale."""
    from scipy import ndimage

    from pipeline.render import render_frame
    tex = TextureSpec("checker", (0.1, 0.1, 0.1), (0.9, 0.9, 0.9), uv_scale=1.5)
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse", texture=tex),
                       transform=Transform(translate=(0.0, -1.0, 0.0), scale=(6.0, 1.0, 6.0)))
    ball = ObjectSpec("ball", MeshSpec("sphere"), MaterialSpec("diffuse", base_color=(0.8, 0.3, 0.2)),
                      transform=Transform(scale=(0.6, 0.6, 0.6)))
    cams = tuple(CameraSpec(origin=(0.5 * f, 3.0, 4.0), target=(0.0, -1.0, 0.0), fov=50.0) for f in range(2))
    spec = SceneSpec("outdoor", 5, (ball, floor), (LightSpec("constant", {"radiance": (1.0, 1.0, 1.0)}),), cams)
    c = cfg(res=(32, 24), spp=4, ref_spp=512, ref_passes=16, layer_levels=0)
    f0, f1 = render_frame(spec, 0, c), render_frame(spec, 1, c)
    m = f1["guides_motion"].astype(np.float64)
    assert np.abs(m).max() > 1.5
    # static diffuse unoccluded: all samples of the pixel and its neighbours hit the floor
    normal = f1["features"][..., G["normal"]]
    is_floor = np.all((normal[..., 1] > 1 - 1e-6) & (f1["features"][..., 3] > 0), axis=-1)    # the plane's normal
    sel0 = ndimage.binary_erosion(is_floor, iterations=2)
    img0, img1 = f0["reference"].astype(np.float64), f1["reference"].astype(np.float64)
    errs = {}
    for alpha in (0.0, 0.8, 1.0, 1.2):
        ok, warped = _warp(img0, m, alpha)
        sel = sel0 & _warp(img0, m, 1.0)[0]
        errs[alpha] = np.abs(warped - img1)[sel].mean()
    assert sel.sum() > 200, sel.sum()
    assert errs[1.0] < 0.35 * errs[0.0], errs
    assert errs[1.0] < errs[0.8] and errs[1.0] < errs[1.2], errs


def test_seeds_independent_and_reproducible(mi, static_frame):
    from pipeline.render import render_frame
    spec, out = static_frame
    ora = oracle(mi, spec, 0, 4096, 31337)
    sd = np.sqrt(pixel_sample_var(out["radiance"])) + 1e-6
    noises = {"inputs": (out["radiance"][:, :, :8].mean(2) - ora) / sd * math.sqrt(8),
              "reference": (out["reference"] - ora) / sd * math.sqrt(256)}
    for lvl in range(6):
        noises[f"layer{lvl}"] = (out["layers"][lvl] - ora) / sd * math.sqrt(2 ** lvl)
    hit = out["features"][..., 3].min(axis=2) > 0
    names = sorted(noises)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            r = np.corrcoef(noises[a][hit].ravel(), noises[b][hit].ravel())[0, 1]
            assert abs(r) < 0.3, (a, b, r)
    # same seed: identical bytes; another scene seed: different noise
    again = render_frame(spec, 0, cfg(spp=32, oracle_spp=64))
    for k, v in out.items():
        if k != "meta":
            assert v.tobytes() == again[k].tobytes(), k
    other = render_frame(ball_scene(seed=8), 0, cfg(spp=32, ref_spp=0, layer_levels=1))
    assert other["radiance"].tobytes() != out["radiance"].tobytes()


def test_early_stop_reference(mi):
    from pipeline.render import render_frame
    out = render_frame(ball_scene(), 0, cfg(ref_spp=1024, ref_passes=64, ref_min_passes=16,
                                             ref_target_rel_stderr=0.05, layer_levels=0, spp=2))
    m = out["meta"]
    assert m["reference_spp"] < 1024 and m["reference_spp"] % 16 == 0
    assert m["reference_rel_stderr"] <= 0.05
    # with an unreachable target all passes run
    out = render_frame(ball_scene(), 0, cfg(ref_spp=256, ref_passes=16, ref_target_rel_stderr=1e-6,
                                             layer_levels=0, spp=2))
    assert out["meta"]["reference_spp"] == 256 and out["meta"]["reference_rel_stderr"] > 1e-6


# -------------------------------------------------------------------------------------------------
# hard cases
def test_black_scene_is_zero(mi):
    from pipeline.render import render_frame
    spec = SceneSpec("indoor", 1, ball_scene().objects, (), ball_scene().cameras)
    out = render_frame(spec, 0, cfg(ref_spp=32, ref_passes=16, spp=2, layer_levels=3))
    for k in ("radiance", "layers", "reference", "reference_stderr"):
        assert np.all(out[k] == 0), k
    assert out["meta"]["reference_rel_stderr"] == 0.0
    assert out["features"][..., 3].max() > 0   # the geometry is there


def test_tiny_bright_emitter_finite(mi):
    from pipeline.render import render_frame
    bulb = ObjectSpec("bulb", MeshSpec("sphere"), MaterialSpec("diffuse", base_color=(0.0, 0.0, 0.0)),
                      transform=Transform(translate=(0.0, 0.0, 1.5), scale=(0.03, 0.03, 0.03)),
                      emitter_radiance=(3e6, 3e6, 3e6))
    spec = SceneSpec("indoor", 2, ball_scene().objects + (bulb,), (), ball_scene().cameras)
    out = render_frame(spec, 0, cfg(spp=16, ref_spp=32, ref_passes=16, layer_levels=3))
    assert out["radiance"].max() > 1e5 and np.isfinite(out["radiance"]).all()
    assert out["reference"].max() > 1e3 and np.isfinite(out["reference"]).all()
    assert out["meta"]["nonfinite_inputs"] == 0


def test_sun_in_view_finite(mi):
    from pipeline.render import render_frame
    # (0, 0.6, 0.8) is above the horizon whether the sky is y-up or (Mitsuba 3.9's sunsky) z-up
    d = np.array([0.0, 0.6, 0.8])
    cam = CameraSpec(origin=(0.0, 0.0, 0.0), target=tuple(d * 10), fov=3.0)
    spec = SceneSpec("outdoor", 4, (), (LightSpec("sunsky", {"sun_direction": tuple(d), "sun_scale": 20.0}),), (cam,))
    out = render_frame(spec, 0, cfg(res=(16, 16), spp=16, ref_spp=32, ref_passes=16, layer_levels=2))
    assert np.isfinite(out["radiance"]).all() and np.isfinite(out["reference"]).all()
    assert out["radiance"].max() > 1e5, out["radiance"].max()


def test_nan_injected_by_hook_is_counted(mi):
    from pipeline.render import render_frame

    def hook(L, F):
        L[::97, 1] = np.nan
        L[5, 0] = np.inf
        F[7, 3] = np.nan

    out = render_frame(ball_scene(), 0, cfg(spp=4, ref_spp=0, layer_levels=0), sample_hook=hook)
    n = RES[0] * RES[1] * 4
    expected = len(range(0, n, 97)) + (0 if 5 % 97 == 0 else 1) + (0 if 7 % 97 == 0 else 1)
    assert out["meta"]["nonfinite_inputs"] == expected
    r = out["radiance"].reshape(-1, 3)
    assert np.isfinite(r).all() and np.all(r[::97] == 0) and r[5, 0] == np.float32(1e8)
    assert np.isfinite(out["features"]).all() and out["features"].reshape(-1, 17)[7, 3] == 0


def test_nan_emitter_counted_in_every_stream(mi):
    """A real NaN from the renderer (an environment emitter with NaN radiance) is counted and replaced."""
    from pipeline.render import render_frame

    def poison(scene):
        p = mi.traverse(scene)
        key = next(k for k in p.keys() if k.endswith("radiance.value"))
        p[key] = mi.Color3f(float("nan"), 1.0, 1.0) if "Color" in type(p[key]).__name__ else float("nan")
        p.update()

    out = render_frame(ball_scene(), 0, cfg(spp=4, ref_spp=32, ref_passes=16, layer_levels=2),
                       on_scene_loaded=poison)
    m = out["meta"]
    assert m["nonfinite_inputs"] > 0 and m["nonfinite_layers"] > 0 and m["nonfinite_reference"] > 0
    for k in ("radiance", "features", "layers", "reference", "reference_stderr"):
        assert np.isfinite(out[k]).all(), k


def test_bad_frame_and_config_type():
    from pipeline.errors import ConfigError, RenderError
    from pipeline.render import render_frame
    with pytest.raises(RenderError, match="out of range"):
        render_frame(ball_scene(), 1, cfg())
    with pytest.raises(ConfigError, match="RenderConfig"):
        render_frame(ball_scene(), 0, {"spp": 8})


def test_points_inside_the_near_plane_have_no_projection():
    """A point in front of the camera but nearer than the near plane (which the sensor clips) projects to
    NaN, so its motion is 0 rather than a vector beyond float16 (found by the hard-case ``motion``)."""
    from scene_gen import projection as cam_geom
    from scene_gen.spec import CameraSpec
    cam = CameraSpec(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, 1.0), up=(0.0, 1.0, 0.0), fov=45.0)
    m = cam_geom.world_to_clip(cam, (64, 64))
    near = cam_geom.NEAR
    pts = np.array([[1.0, 0.5, 0.5 * near], [1.0, 0.5, 2.0 * near], [0.0, 0.0, -1.0], [0.1, 0.0, 3.0]])
    px = cam_geom.project_pixels(m, pts, (64, 64))
    assert np.isnan(px[0]).all() and np.isnan(px[2]).all()
    assert np.isfinite(px[1]).all() and np.isfinite(px[3]).all() and np.abs(px[1]).max() > 1000
    d = cam_geom.project_pixels(m, np.array([[0.0, 0.0, 1.0]]), (64, 64), w=0.0)    # a direction: the centre
    np.testing.assert_allclose(d, [[32.0, 32.0]])


# -------------------------------------------------------------------------------------------------
# the input loop on the device: its own path tracer, launches, read-backs, the NaN rule and the guides
def mixed_scene():
    """ball_scene plus glass, a mirror, a rough metal and a small area light: delta, glossy and emitting
    surfaces, so every branch of the path tracer runs."""
    extra = (ObjectSpec("glass", MeshSpec("sphere"), MaterialSpec("dielectric"),
                        transform=Transform(translate=(-1.3, -0.5, 0.6), scale=(0.45, 0.45, 0.45))),
             ObjectSpec("mirror", MeshSpec("box"), MaterialSpec("conductor"),
                        transform=Transform(translate=(1.4, -0.6, -0.4), scale=(0.4, 0.4, 0.4))),
             ObjectSpec("metal", MeshSpec("box"), MaterialSpec("roughconductor", roughness=0.2),
                        transform=Transform(translate=(0.4, -0.8, 1.3), scale=(0.2, 0.2, 0.2))),
             ObjectSpec("lamp", MeshSpec("sphere"), MaterialSpec("diffuse", base_color=(0.0, 0.0, 0.0)),
                        transform=Transform(translate=(0.6, 0.9, 0.9), scale=(0.15, 0.15, 0.15)),
                        emitter_radiance=(40.0, 30.0, 20.0)))
    return ball_scene(extra=extra)


def test_path_tracer_is_mitsubas_path_integrator(mi):
    """pipeline.primary_path gives the per-sample radiance of the scene's own path integrator from the
    same sampler state (bit for bit on LLVM), and its first-hit record is scene.ray_intersect's hit."""
    import drjit as dr

    from pipeline import primary_path
    from pipeline import render as R
    from pipeline.render import inputs as I
    fs = R.FrameScene(mixed_scene(), 0, cfg(spp=4, ref_spp=0, layer_levels=0))
    H, s_per = RES[1], 4

    def rays():
        return I._camera_rays(fs, I._Reads(fs, I._wave_params(fs, 0, 0.0), H * RES[0] * s_per), 4242, H, s_per)

    sampler, ray, _w, _f, _a = rays()
    si = fs.scene.ray_intersect(ray, mi.RayFlags.All, True)
    alb = si.bsdf(ray).eval_diffuse_reflectance(si, si.is_valid())
    want, want_valid, _ = fs.integrator.sample(fs.scene, sampler, ray, None, True)
    dr.eval(want, want_valid, si, alb)
    sampler, ray, _w, _f, _a = rays()
    got, got_valid, prim = primary_path.trace(mi, fs.scene, sampler, ray, *fs.integrator_depths)
    dr.eval(got, got_valid, prim)
    a, b = np.asarray(want), np.asarray(got)
    assert b.max() > 1.0 and np.isfinite(b).all()                      # the lamp is seen, directly or not
    if mi.variant().startswith("llvm"):
        assert a.tobytes() == b.tobytes() and np.array_equal(np.asarray(want_valid), np.asarray(got_valid))
    else:                                                             # other backends: the same up to rounding
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6)
    hit = np.asarray(si.is_valid())
    assert np.array_equal(np.asarray(prim["hit"]), hit) and 0.2 < hit.mean() < 1.0
    assert np.array_equal(np.asarray(prim["shape"]), np.asarray(dr.reinterpret_array(mi.UInt32, si.shape)))
    for k, v in (("p", si.p), ("n", si.sh_frame.n), ("t", si.t), ("albedo", alb)):
        assert np.array_equal(np.asarray(prim[k])[..., hit], np.asarray(v)[..., hit]), k


def test_input_loop_launches_and_reads(mi):
    """drjit's kernel history (LLVM): a still's inputs take one kernel a wavefront plus one for the
    guides, at most two more than mi.render of the same samples, and one read-back a wavefront; a
    moving frame adds per time slice only what moving the objects costs (set_time)."""
    from pipeline.bench_render import launch_counts
    c = launch_counts(ball_scene(motion=True), cfg(spp=8, ref_spp=0, layer_levels=0, time_slices=2))
    ours, theirs = c["static"]["input_loop"], c["static"]["mi_render"]
    assert ours["kernels"] <= theirs["kernels"] + 2, c["static"]
    assert ours["jit"] == 2 and ours["reads"] == ours["wavefronts"] == 1, ours
    ours = c["moving"]["input_loop"]
    assert ours["reads"] == ours["wavefronts"] == 2 and ours["own_kernels"] == 2 + 1, c["moving"]
    # a still split into row chunks: a kernel and a read a chunk, a guide kernel a chunk
    chunked = launch_counts(ball_scene(), cfg(spp=8, ref_spp=0, layer_levels=0, max_wavefront=1024))
    ours = chunked["static"]["input_loop"]
    assert ours["wavefronts"] == 4 and ours["reads"] == 4 and ours["jit"] == 2 * 4, ours


def test_device_nan_rule_is_the_host_rule(mi):
    """The input kernel's NaN/Inf rule gives what sanitize_samples gives, bit for bit, sign of zero included."""
    from types import SimpleNamespace

    import drjit as dr

    from pipeline.render import sanitize_samples
    from pipeline.render.inputs import _sanitize_columns
    rng = np.random.default_rng(3)
    L = (rng.standard_normal((64, 3)) * 10).astype(np.float32)
    F = rng.standard_normal((64, 17)).astype(np.float32)
    L[1, 0], L[2, 1], L[3, 2], L[4] = np.nan, np.inf, -np.inf, (np.inf, np.nan, 2e9)
    L[5, 0], L[6, 1], F[7, 3], F[8, 0], F[9, 16], F[10, 5] = 3e9, -0.0, np.nan, np.inf, -np.inf, -0.0
    want_L, want_F, count = sanitize_samples(L.copy(), F.copy(), 1e8)
    fs = SimpleNamespace(dr=dr, cfg=SimpleNamespace(max_value=1e8))
    Lc, Fc = _sanitize_columns(fs, [mi.Float(L[:, c]) for c in range(3)], [mi.Float(F[:, c]) for c in range(17)])
    got_L = np.stack([np.asarray(v) for v in Lc], axis=1)
    got_F = np.stack([np.asarray(v) for v in Fc], axis=1)
    assert count == 7 and got_L.tobytes() == want_L.tobytes() and got_F.tobytes() == want_F.tobytes()
    assert want_L[5, 0] == np.float32(3e9) and want_L[2, 1] == np.float32(1e8) and np.all(want_L[4] == 0)


def test_guides_are_sample_means_across_slices_and_chunks(mi):
    """The guides computed on the device are the per-pixel means of the stored samples (to an ulp or two)
    across time slices and row chunks, and the samples are those of the host-side path (sample_hook)."""
    from pipeline import render as R
    from pipeline.render import inputs as I
    c = cfg(res=(48, 32), spp=8, ref_spp=0, layer_levels=0, time_slices=4, max_wavefront=1024)
    fs = R.FrameScene(ball_scene(motion=True, defocus=True), 0, c)
    dev = R.input_samples(fs)
    host = R.input_samples(fs, sample_hook=lambda L, F: None)
    assert len(list(I._input_wavefronts(fs))) == 4 * 4 and dev["nonfinite"] == host["nonfinite"] == 0
    for k in ("radiance", "features"):
        assert dev[k].tobytes() == host[k].tobytes(), k
    f = dev["features"]
    for g in R.GUIDE_GROUPS:
        want = f[..., G[g]].astype(np.float64).mean(axis=2)
        np.testing.assert_allclose(dev[f"guides_{g}"], want, rtol=3e-7, atol=1e-7, err_msg=g)
        np.testing.assert_allclose(dev[f"guides_{g}"], host[f"guides_{g}"], rtol=3e-7, atol=1e-7, err_msg=g)
    assert np.abs(dev["guides_motion"]).max() > 0.1


def test_moving_objects_keep_their_normals_to_the_bit(mi):
    """Moving an object (a translation) keeps its vertex normals bit for bit: Mitsuba's own recomputation
    after a position update adds with atomics in a varying order, which put 1-4 ulp of run-to-run noise
    into every sample that hit a moving object; so a moving frame renders the same bits twice."""
    from pipeline import render as R
    c = cfg(res=(16, 16), spp=4, ref_spp=0, layer_levels=0, time_slices=4)
    fs = R.FrameScene(ball_scene(motion=True), 0, c)
    params = fs.loaded._params
    rest = np.array(params["ball.vertex_normals"])
    for i in range(40):
        fs.set_time((i % 4 + 1) / 4)
        assert np.array(params["ball.vertex_normals"]).tobytes() == rest.tobytes(), i
    first = R.input_samples(fs)
    for _ in range(3):
        again = R.input_samples(fs)
        for k in ("radiance", "features"):
            assert again[k].tobytes() == first[k].tobytes(), k


# -------------------------------------------------------------------------------------------------
# launches within drjit's 2**32 samples
def test_launch_plan_splits_only_what_exceeds_2_to_the_32_samples():
    from pipeline.render import MAX_LAUNCH_SAMPLES, launch_plan, launch_seed
    assert MAX_LAUNCH_SAMPLES == 2 ** 32 - 1
    px = 1920 * 1080
    assert launch_plan(px, 128) == [128]                        # a pass of the default 32: one launch
    assert launch_plan(px, 4096) == [2048, 2048]                # 8.5e9 samples: two
    assert launch_plan(px, 2071) == [2071] and launch_plan(px, 2072) == [1036, 1036]
    for pixels, spp in ((px, 65536), (3840 * 2160, 4096), (7, 10 ** 9), (1, 2 ** 33)):
        plan = launch_plan(pixels, spp)
        assert sum(plan) == spp and max(plan) * pixels <= MAX_LAUNCH_SAMPLES and max(plan) - min(plan) <= 1
        assert len(plan) == -(-pixels * spp // (MAX_LAUNCH_SAMPLES // pixels * pixels))
    with pytest.raises(ValueError, match="exceeds"):
        launch_plan(10, 1, limit=9)
    assert launch_seed(5, 0) == 5 and len({launch_seed(5, i) for i in range(100)}) == 100
    assert all(0 <= launch_seed(2 ** 31 - 1, i) < 2 ** 31 for i in range(10))


def test_a_render_split_into_launches_is_the_same_estimate(mi, monkeypatch):
    """With the launch limit lowered to a few samples a pixel, a reference renders in several launches
    per pass: its mean agrees with Mitsuba's own mi.render (z-test), and it is not the unsplit image."""
    from pipeline.render import launches, render_frame
    spec = ball_scene()
    c = cfg(spp=2, ref_spp=256, ref_passes=4, ref_min_passes=2, layer_levels=0)
    whole = render_frame(spec, 0, c)
    W, H = RES
    monkeypatch.setattr(launches, "MAX_LAUNCH_SAMPLES", W * H * 24)        # 64-spp passes: 3 launches each
    assert launches.launch_plan(W * H, 64) == [22, 21, 21]
    split = render_frame(spec, 0, c)
    assert split["meta"]["reference_spp"] == 256
    assert split["reference"].tobytes() != whole["reference"].tobytes()
    assert split["radiance"].tobytes() == whole["radiance"].tobytes()       # the input loop is not mi.render
    ora, var_ora = oracle(mi, spec, 0, 1024, 4242, with_var=True)
    var_split = split["reference_stderr"].astype(np.float64) ** 2          # variance of the pixel's mean
    assert zmax(split["reference"].astype(np.float64), var_split, ora, var_ora / 1024) < 5


@pytest.mark.gpu
def test_cuda_and_llvm_estimates_of_one_scene_agree(tmp_path):
    """The same generated scene rendered by Mitsuba's CUDA and LLVM variants (each in its own process,
    scripts/device_check.py's estimate): the image and 4x4-block means agree within the z-test above."""
    import os
    import subprocess
    import sys
    from pathlib import Path
    root = Path(__file__).resolve().parent.parent
    est = {}
    for v in ("cuda_ad_rgb", "llvm_ad_rgb"):
        out = tmp_path / f"{v}.npz"
        r = subprocess.run([sys.executable, str(root / "scripts" / "device_check.py"), "--estimate", str(out)],
                           env={**os.environ, "MI_VARIANT": v, "PYTHONPATH": str(root)}, cwd=root,
                           capture_output=True, text=True, timeout=900)
        assert r.returncode == 0, r.stderr[-2000:]
        est[v] = dict(np.load(out))
    a, b = est["cuda_ad_rgb"], est["llvm_ad_rgb"]
    assert zmax(a["mean"], a["var"], b["mean"], b["var"]) < 5


# -------------------------------------------------------------------------------------------------
# the pixel filter
def fine_checker_scene():
    """A floor of checks finer than a pixel seen from above: every pixel's filter footprint straddles checks,
    so a wrong filter shows in every pixel (a pixel inside one check would be the same under any filter)."""
    cam = CameraSpec(origin=(0.0, 3.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, -1.0), fov=50.0)
    tex = TextureSpec("checker", (0.05, 0.05, 0.05), (0.9, 0.9, 0.9), uv_scale=16.0)
    floor = ObjectSpec("floor", MeshSpec("plane"), MaterialSpec("diffuse", texture=tex),
                       transform=Transform(scale=(4.0, 1.0, 4.0)))
    return SceneSpec("indoor", 3, (floor,), (LightSpec("constant", {"radiance": (1.0, 1.0, 1.0)}),), (cam,))


def test_gaussian_filter_pixels_are_mitsubas_filtered_pixels(mi):
    """With ``filter: gaussian`` the mean of a pixel's input samples (film positions drawn from the filter)
    and the reference estimate the pixel ``mi.render`` gives with Mitsuba's Gaussian film, pixel by pixel,
    and the reference's standard error counts the filter's gain; the box filter's inputs do not."""
    from pipeline.render import render_frame
    from pipeline.render.scene import FilmFilter
    from scene_gen import to_mitsuba
    spec = fine_checker_scene()
    gain = FilmFilter(mi, mi.load_dict({"type": "gaussian"}), "gaussian").gain
    assert 2.9 < gain < 3.3                     # (integral f)^2 / integral f^2 of the stddev-0.5 Gaussian, squared
    scene = to_mitsuba.load(spec, 0, RES, rfilter="gaussian")
    ora = np.mean([np.asarray(mi.render(scene, spp=256, seed=s), np.float64)[..., :3] for s in range(8)], axis=0)
    frac = {}
    for filt in ("gaussian", "box"):
        out = render_frame(spec, 0, cfg(spp=64, filter=filt, ref_spp=1024, ref_passes=16, layer_levels=0))
        rad = out["radiance"].astype(np.float64)
        v = rad.var(axis=2, ddof=1)         # a sample's variance; the oracle's mean of 2048 filtered samples: v / (gain 2048)
        z = (rad.mean(axis=2) - ora) / np.sqrt(v / 64 + v / (gain * 2048))
        frac[filt] = float(np.mean(np.abs(z) > 3))
        if filt == "gaussian":
            assert np.abs(z).mean() < 1.0, np.abs(z).mean()
            ref, se = out["reference"].astype(np.float64), out["reference_stderr"].astype(np.float64)
            zr = (ref - ora) / np.sqrt(se ** 2 + v / (gain * 2048))
            assert np.mean(np.abs(zr) > 3) < 0.02, np.mean(np.abs(zr) > 3)
            ratio = (se ** 2).mean() / (v / (gain * 1024)).mean()      # the error the filtered samples have
            assert 0.7 < ratio < 1.4, ratio
    assert frac["gaussian"] < 0.02 and frac["box"] > 0.1, frac
    # a launch of the Gaussian film samples its 2-pixel border too: launches are planned on those pixels
    from pipeline.render import FrameScene
    assert FrameScene(spec, 0, cfg(filter="gaussian", ref_spp=0, layer_levels=0)).launch_pixels == (RES[0] + 4) * (RES[1] + 4)
