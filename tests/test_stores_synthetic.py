"""A realistic synthetic frame generator for the store tests (and the store benchmark), plus its checks.

``synthetic_frame(seed, h, w, spp)`` returns a dict shaped exactly like ``stores.contract.FRAME_ARRAYS``
(channel-last numpy arrays) plus ``meta`` (``FRAME_META``): a few objects (discs and boxes) over a
miss background, each with a constant normal, albedo, specular colour and roughness and a depth
gradient; HDR radiance with heavy-tailed per-sample noise, rare fireflies (x1e3..1e5) and an optional
sun disc (~1e5); sample layers drawn from the same distribution; a reference with its standard error;
per-pixel guides; camera matrices. Features that a scene does not need stay exactly 0 (lens, coc,
time without defocus/motion), as the renderer writes them. Not a renderer: it only has the statistics
that matter to a store (value ranges, constant regions, heavy tails).
"""
from __future__ import annotations

import json

import numpy as np

from stores.contract import FEATURE_NAMES, FRAME_ARRAYS, FRAME_META, LAYER_SPP, NUM_FEATURES


def _look_at(origin, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    o, t, u = (np.asarray(v, np.float64) for v in (origin, target, up))
    f = t - o
    f /= np.linalg.norm(f)
    r = np.cross(u, f)
    r /= np.linalg.norm(r)
    u2 = np.cross(f, r)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u2, f, o
    return m


def synthetic_frame(seed: int = 0, h: int = 32, w: int = 32, spp: int = 8, *, frame: int = 0,
                    num_frames: int = 1, motion: bool | None = None, defocus: bool | None = None,
                    sun: bool | None = None, scene_seed: int | None = None) -> dict:
    """One frame: ``radiance (float32, HWS3)``, ``features (float32, HWS17)``, ``layers (float32, LHW3)``,
    ``reference``/``reference_stderr``/``guides_albedo``/``guides_normal`` (float32, HW3),
    ``guides_depth`` (HW1), ``guides_motion`` (HW2), ``camera_to_world``/``world_to_clip`` (float64, 44),
    ``meta`` (dict). Frames of one clip share ``scene_seed``; objects move by ``frame * velocity``."""
    scene_seed = seed if scene_seed is None else scene_seed
    srng = np.random.default_rng(np.random.SeedSequence([scene_seed, 0]))
    rng = np.random.default_rng(np.random.SeedSequence([scene_seed, 1, frame]))
    motion = bool(srng.random() < 0.5) if motion is None else motion
    defocus = bool(srng.random() < 0.5) if defocus is None else defocus
    sun = bool(srng.random() < 0.3) if sun is None else sun

    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    obj = np.full((h, w), -1, np.int32)
    n_obj = int(srng.integers(3, 7))
    props = []
    for k in range(n_obj):
        cx, cy = srng.uniform(0, w), srng.uniform(0, h)
        vel = srng.uniform(-2, 2, size=2) if motion else np.zeros(2)
        cx, cy = cx + vel[0] * frame, cy + vel[1] * frame
        r = srng.uniform(0.15, 0.4) * min(h, w)
        if k % 2:
            mask = (np.abs(xx - cx) < r) & (np.abs(yy - cy) < 0.7 * r)
        else:
            mask = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        obj[mask] = k
        n = srng.normal(size=3)
        props.append(dict(
            normal=n / np.linalg.norm(n), albedo=srng.uniform(0, 1, 3), spec=srng.uniform(0, 1, 3),
            rough=srng.uniform(0, 1), depth=srng.uniform(1, 50), grad=srng.normal(0, 0.05, 2),
            light=10 ** srng.uniform(-1, 1.5), vel=vel))

    hit = obj >= 0
    f = np.zeros((h, w, spp, NUM_FEATURES), np.float32)
    mean = np.zeros((h, w, 3), np.float32)
    sky = np.array([0.4, 0.6, 1.0], np.float32) * 2.0
    mean[~hit] = sky
    for k, p in enumerate(props):
        m = obj == k
        f[m, :, 0:3] = p["normal"]
        f[m, :, 3] = (p["depth"] + p["grad"][0] * xx[m] + p["grad"][1] * yy[m])[:, None]
        f[m, :, 4:7] = p["albedo"]
        f[m, :, 7:10] = p["spec"]
        f[m, :, 10] = p["rough"]
        if motion:
            f[m, :, 11] = -p["vel"][0]      # p_prev - p_cur
            f[m, :, 12] = -p["vel"][1]
        mean[m] = p["albedo"] * p["light"]
    if sun:
        cx, cy, r = srng.uniform(0, w), srng.uniform(0, h), max(1.5, 0.08 * min(h, w))
        disc = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        mean[disc] = np.array([1.2e5, 1.0e5, 0.8e5], np.float32)

    def draw(n_samples: int, shape_prefix=(h, w)) -> np.ndarray:
        # heavy-tailed: exponential noise around the mean + rare fireflies
        noise = rng.exponential(1.0, size=(*shape_prefix, n_samples, 3)).astype(np.float32)
        x = mean[:, :, None, :] * noise
        fire = rng.random((*shape_prefix, n_samples)) < 0.003
        x[fire] *= rng.uniform(1e3, 1e5, size=(int(fire.sum()), 1)).astype(np.float32)
        x[rng.random((*shape_prefix, n_samples)) < 0.05] = 0.0      # absorbed paths
        return x

    radiance = draw(spp)
    if defocus:
        f[..., 13] = np.where(hit[..., None], (f[..., 3] - 10.0) * 0.3, 0.0)
        ang = rng.uniform(0, 2 * np.pi, (h, w, spp))
        rad = np.sqrt(rng.uniform(0, 1, (h, w, spp)))
        f[..., 14], f[..., 15] = rad * np.cos(ang), rad * np.sin(ang)
    if motion:
        f[..., 16] = (np.arange(spp)[None, None, :] + rng.uniform(0, 1, (h, w, spp))) / spp
    layers = np.stack([draw(n).mean(axis=2) for n in LAYER_SPP]).astype(np.float32)
    ref_spp = 4096
    reference = (mean * rng.normal(1.0, 0.01, size=mean.shape)).astype(np.float32)
    stderr = (np.abs(reference) * 0.01 + 1e-4).astype(np.float32)

    cam = _look_at(srng.uniform(-5, 5, 3) + np.array([0, 0, -10.0]) + frame * 0.1, (0, 0, 0))
    proj = np.diag([1.5, 1.5, 1.0, 0.0])
    proj[2, 3], proj[3, 2] = -0.01, 1.0
    world_to_clip = proj @ np.linalg.inv(cam)
    meta = dict(
        scene_json=json.dumps({"kind": "synthetic", "seed": int(scene_seed), "objects": n_obj}),
        scene_seed=int(scene_seed), frame=int(frame), num_frames=int(num_frames), has_motion=motion,
        has_defocus=defocus, nonfinite_inputs=0, nonfinite_layers=0, nonfinite_reference=0,
        reference_spp=ref_spp, reference_rel_stderr=0.01, render_seconds=float(rng.uniform(0.5, 2.0)))
    for k, t in FRAME_META.items():          # keys added to the contract since (e.g. ``case``): '' / 0 / False
        meta.setdefault(k, t())
    return dict(
        radiance=radiance, features=f, layers=layers, reference=reference, reference_stderr=stderr,
        guides_albedo=f[..., 4:7].mean(axis=2), guides_normal=f[..., 0:3].mean(axis=2),
        guides_depth=f[..., 3:4].mean(axis=2), guides_motion=f[..., 11:13].mean(axis=2),
        camera_to_world=cam, world_to_clip=world_to_clip, meta=meta)


def test_synthetic_frame_matches_contract():
    fr = synthetic_frame(3, 16, 24, 4)
    dims = {"H": 16, "W": 24, "S": 4, "L": len(LAYER_SPP)}
    for name, (tmpl, dtype) in FRAME_ARRAYS.items():
        shape = tuple(dims.get(d, d) for d in tmpl)
        assert fr[name].shape == shape, name
        assert fr[name].dtype == np.dtype(dtype), name
        assert np.isfinite(fr[name]).all(), name
    assert set(fr["meta"]) == set(FRAME_META)
    assert len(FEATURE_NAMES) == 17


def test_synthetic_frame_is_deterministic_and_hdr():
    a, b = synthetic_frame(5, 16, 16, 8, sun=True), synthetic_frame(5, 16, 16, 8, sun=True)
    np.testing.assert_array_equal(a["radiance"], b["radiance"])
    assert a["radiance"].max() > 1e5            # sun disc and fireflies
    assert (a["radiance"] == 0).any()           # absorbed paths


def stored(name: str, a, layout) -> np.ndarray:
    """What a store of ``layout`` returns (``read_frame``) for contract array ``name`` written as
    ``a``: exact for lossless arrays; the encoding's rounding for lossy ones (``compact``: the
    mantissa rounded to 9 bits, as numcodecs' BitRound does; ``compact2`` and ``compact3``: each feature
    to its group's bits first; float16 features; log16 codes)."""
    from stores import codecs
    from stores.schema import ARRAY_BY_SOURCE
    spec = ARRAY_BY_SOURCE[name]
    if not spec.image:
        return np.asarray(a)
    a = np.asarray(a, np.float32)
    if name == "radiance" and layout.radiance_encoding == "log16":
        return codecs.decode_log16(codecs.encode_log16(a))
    chain = spec.chain(layout)
    keep = chain.keepbits
    if chain.channel_keepbits is not None:      # compact2's features: the writer rounds each channel
        a = codecs.bitround_channels(a, chain.channel_keepbits, -1)
    if keep is not None:
        a = codecs.bitround(a, keep)
    if spec.storage_dtype(layout) == "float16":
        a = a.astype(np.float16)
        if chain.codec_keepbits is not None:   # the codec's own BitRound (not compact3's): a no-op but for
            a = codecs.bitround(a, keep)       # float16 subnormals (|x| < 2**-14)
        a = a.astype(np.float32)
    return a
