"""The per-sample inputs of a frame: one drjit kernel a wavefront traces every camera ray once for its
radiance and its primary hit, computes the 17 features, applies the NaN/Inf rule and writes the 20
floats of each sample straight into one buffer; a small kernel adds the per-pixel guides.

Film positions: with the ``box`` filter each sample lies uniformly inside its pixel (a pixel's mean is
the estimator ``mi.render`` uses); with another filter (``gaussian``) a sample's offset from the pixel
centre is drawn with density proportional to the film's filter (:class:`pipeline.render.scene.FilmFilter`),
so the mean of a pixel's samples estimates the same filtered pixel as ``mi.render`` with that filter.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from pipeline.render.scene import K_CLIP, K_COC, K_EYE, K_FOCUS, K_FWD, K_PREV, K_VIEW, FrameScene
from pipeline.render.settings import STREAM_INPUTS, slice_times, stream_seed, time_rng
from scene_gen import projection as cam_geom
from stores.contract import FEATURE_GROUPS, NUM_FEATURES

# Slots of a wavefront's parameters (UInt32; the two times by their float32 bits), beside the frame's constants
# (``pipeline.render.scene.K_*``). Values reach the kernel through memory, so one compiled kernel serves every
# wavefront, slice and frame, at one upload a wavefront.
_W_ROW0, _W_TAU, _W_T = 0, 1, 2
# The per-pixel guides (means over a pixel's samples) and, after them, a pixel's non-finite sample count:
# the block that follows a wavefront's samples in its buffer when the wavefront completes its pixels.
GUIDE_GROUPS = ("albedo", "normal", "depth", "motion")
_GUIDE_FEATURES = [i for g in GUIDE_GROUPS for i in range(FEATURE_GROUPS[g].start, FEATURE_GROUPS[g].stop)]
_SAMPLE_FLOATS = 3 + NUM_FEATURES


class _Reads:
    """The frame's constants (``fs.consts``, ``fs.consts_u``) and a wavefront's parameters (``wp``) as
    one wavefront's kernel reads them. Each read is a gather at an index that depends on the lane but is
    always the slot: drjit serves a gather at a literal index by copying the value out in a launch of
    its own before the kernel, one launch a constant."""

    def __init__(self, fs: FrameScene, wp, n: int):
        dr, self.mi = fs.dr, fs.mi
        self.dr, self.fs, self.wp = dr, fs, wp
        self.zero = (dr.arange(fs.mi.UInt32, n) >> 16) >> 16          # 0 in every lane, not a literal

    def f(self, i: int):
        return self.dr.gather(self.mi.Float, self.fs.consts, self.zero + i)

    def u(self, i: int):
        return self.dr.gather(self.mi.UInt32, self.fs.consts_u, self.zero + i)

    def w(self, i: int):
        return self.dr.gather(self.mi.UInt32, self.wp, self.zero + i)


def _wave_params(fs: FrameScene, row0: int, t: float):
    """One upload a wavefront: its first row, scene time ``tau`` and shutter fraction ``t``. (The sampler
    seed is passed to ``sampler.seed`` as a number, which makes it opaque itself.)"""
    times = np.array([fs.tau(t), t], np.float32).view(np.uint32)
    return fs.mi.UInt32(np.array([row0, times[0], times[1]], np.uint32))


def _camera_rays(fs: FrameScene, rd: _Reads, seed: int, rows: int, s_per: int):
    """The camera rays of one wavefront (``rd``: its :func:`_wave_params`, ``seed``: its sampler seed):
    ``(sampler, ray, weight, film, ap)``.
    Lane ``i`` is sample ``i % s_per`` of pixel ``i // s_per`` (row-major from row ``row0``). The sampler
    is left after the ray's five dimensions (film 2, lens 2, wavelength 1), where the integrator
    continues; the input loop and :func:`_geometry` both start here, so a geometry pass sees exactly
    the rays of the input samples."""
    mi, dr = fs.mi, fs.dr
    W, H = fs.cfg.res
    n = rows * W * s_per
    sampler = fs.sampler
    sampler.seed(int(seed), n)
    pix = dr.arange(mi.UInt32, n) // s_per
    px = mi.Float(pix % W)
    py = mi.Float(pix // W + rd.w(_W_ROW0))
    film = (mi.Point2f(px, py) + _pixel_offsets(fs, sampler.next_2d())) * mi.ScalarPoint2f(1.0 / W, 1.0 / H)
    ap = sampler.next_2d()
    wav = sampler.next_1d()
    ray, weight = fs.sensor.sample_ray_differential(dr.reinterpret_array(mi.Float, rd.w(_W_TAU)), wav, film, ap)
    return sampler, ray, weight, film, ap


def _pixel_offsets(fs: FrameScene, u):
    """A sample's film position inside its pixel (from the pixel's corner) for the uniform 2D sample ``u``:
    ``u`` itself for the box filter, else the pixel centre plus an offset drawn from the film's filter
    (:class:`pipeline.render.scene.FilmFilter`; it may fall in a neighbouring pixel, as Mitsuba's splats do)."""
    ff = fs.film_filter
    if ff is None:
        return u
    return fs.mi.Point2f(0.5 + ff.dist.sample(u.x), 0.5 + ff.dist.sample(u.y))


def _wave(fs: FrameScene, seed: int, wp, rows: int, s_per: int, *, sanitize: bool = True, room: bool = False,
          probe: Callable | None = None):
    """Launch one wavefront (asynchronously; nothing is read here): ``rows`` pixel rows, ``s_per``
    samples a pixel. One drjit kernel traces the camera rays once (:mod:`pipeline.primary_path`: the
    radiance and the primary hit together), computes the 17 features, applies the NaN/Inf rule (unless
    ``sanitize`` is false: the tests' ``sample_hook`` path applies it on the host) and writes the 20
    floats of each sample straight into one buffer: radiance (N×3), then features (N×17), lane-major,
    then, with ``room``, space for the guide block (:func:`_guide_block`). Returns ``(buffer, columns,
    extra)``: ``columns`` the guide features and the non-finite flag of every lane (10 Floats, for
    :func:`_guide_block`), ``extra`` what ``probe(prim=, ray=, film=, ap=)`` asks of the same kernel (a
    dict of drjit values; tests read the primary hits with it)."""
    from pipeline import primary_path
    mi, dr = fs.mi, fs.dr
    W = fs.cfg.width
    n = rows * W * s_per
    rd = _Reads(fs, wp, n)
    sampler, ray, weight, film, ap = _camera_rays(fs, rd, seed, rows, s_per)
    L, _valid, prim = primary_path.trace(mi, fs.scene, sampler, ray, *fs.integrator_depths)
    L = L * weight
    Lc, Fc = [L[0], L[1], L[2]], _feature_columns(fs, rd, prim, ray, ap)
    bad = ~_all_finite(dr, Lc + Fc)
    if sanitize:
        Lc, Fc = _sanitize_columns(fs, Lc, Fc)
    buf = _new_buffer(fs, n * _SAMPLE_FLOATS + (rows * W * (len(_GUIDE_FEATURES) + 1) if room else 0))
    lane = dr.arange(mi.UInt32, n)
    for c, v in enumerate(Lc):
        _write(fs, buf, v, lane * 3 + c)
    for c, v in enumerate(Fc):
        _write(fs, buf, v, lane * NUM_FEATURES + (3 * n + c))
    cols = [Fc[i] for i in _GUIDE_FEATURES] + [dr.select(bad, 1.0, 0.0)]
    extra = probe(prim=prim, ray=ray, film=film, ap=ap) if probe is not None else {}
    dr.eval(buf, *cols, *extra.values())                # the wavefront: one kernel
    return buf, cols, extra


def _new_buffer(fs: FrameScene, size: int):
    """A zeroed buffer of ``size`` float32 values, held as their bits (UInt32) for :func:`_write`."""
    return fs.dr.zeros(fs.mi.UInt32, size)


def _write(fs: FrameScene, buf, value, index) -> None:
    """``buf[index] = value`` (Float ``value``; each index written once) as an OR of its bits into the zeroed
    buffer: exact for every float (-0.0 and NaN included). drjit gives every plain scatter into one buffer a
    kernel of its own (their order), while scatter-reductions into one buffer share the kernel (a float add
    would do as well but drjit skips adding zeros, which loses the sign of -0.0); ``NoConflicts``: no
    atomics, since no two lanes write one element."""
    dr = fs.dr
    dr.scatter_reduce(dr.ReduceOp.Or, buf, dr.reinterpret_array(fs.mi.UInt32, value), index,
                      mode=dr.ReduceMode.NoConflicts)


def _all_finite(dr, cols):
    ok = dr.isfinite(cols[0])
    for v in cols[1:]:
        ok &= dr.isfinite(v)
    return ok


def _sanitize_columns(fs: FrameScene, Lc: list, Fc: list) -> tuple[list, list]:
    """The NaN/Inf rule on a wavefront's columns, in its kernel (:func:`sanitize_samples` is its host form):
    a sample with a NaN radiance component gets radiance 0, +-Inf radiance is clamped to
    +-``cfg.max_value``, a non-finite feature becomes 0."""
    dr = fs.dr
    mv = float(fs.cfg.max_value)
    nan = dr.isnan(Lc[0]) | dr.isnan(Lc[1]) | dr.isnan(Lc[2])
    L = [dr.select(nan, 0.0, dr.select(dr.isinf(v), dr.select(v > 0, mv, -mv), v)) for v in Lc]
    return L, [dr.select(dr.isfinite(v), v, 0.0) for v in Fc]


def _guide_block(fs: FrameScene, buf, rows: int, s_per: int, slices: list) -> None:
    """Launch the guide kernel of a chunk of ``rows`` rows (one lane a pixel) once its last wavefront is
    launched: each pixel's sum over its samples, added in sample order across ``slices`` (the guide
    columns of the chunk's wavefronts, one a time slice), times 1/S (so within an ulp or two of numpy's
    ``features.mean(axis=2)``, whose order of additions varies with the array's layout; the same bits
    for the same inputs); and its non-finite count. Written
    into ``buf`` after the samples: albedo (P×3), normal (P×3), depth (P), motion (P×2), count (P)."""
    mi, dr = fs.mi, fs.dr
    P = rows * fs.cfg.width
    p = dr.arange(mi.UInt32, P)
    acc = [dr.gather(mi.Float, c, p * s_per) for c in slices[0]]
    for k, cols in enumerate(slices):
        acc = _sum_samples(fs, acc, cols, p, s_per, 1 if k == 0 else 0)
    vals = [a * (1.0 / fs.cfg.spp) for a in acc[:-1]] + [acc[-1]]
    off, i = P * s_per * _SAMPLE_FLOATS, 0
    for g in GUIDE_GROUPS:
        width = FEATURE_GROUPS[g].stop - FEATURE_GROUPS[g].start
        for c in range(width):
            _write(fs, buf, vals[i], p * width + (off + c))
            i += 1
        off += P * width
    _write(fs, buf, vals[i], p + off)
    dr.eval(buf)                                        # the guides: one small kernel


def _sum_samples(fs: FrameScene, acc: list, cols: list, p, s_per: int, j0: int) -> list:
    """``acc`` plus ``cols[c][p * s_per + j]`` for j = j0 ... s_per - 1, added one sample after another."""
    mi, dr = fs.mi, fs.dr

    def body(j, *a):
        i = p * s_per + j
        return (j + 1, *(x + dr.gather(mi.Float, c, i) for x, c in zip(a, cols)))

    _, *acc = dr.while_loop((dr.full(mi.UInt32, j0, dr.width(p)), *acc), lambda j, *a: j < s_per, body,
                            labels=("j", *(f"acc{c}" for c in range(len(acc)))), label="guide_means")
    return acc


MOTION_LIMIT = 16     # motion vectors are capped at this many image sizes (see _feature_columns)


def _feature_columns(fs: FrameScene, rd: _Reads, prim: dict, ray, ap) -> list:
    """The 17 features (``stores.contract.FEATURE_NAMES``) of traced lanes, as drjit Float columns (the
    wavefront's own kernel): ``prim`` the primary hits (:func:`pipeline.primary_path.trace`), ``ray`` the
    camera rays, ``ap`` their aperture samples, ``rd`` the constants and wavefront parameters."""
    mi, dr = fs.mi, fs.dr
    Float, V3 = mi.Float, mi.Vector3f
    hit, p = prim["hit"], prim["p"]
    zero = Float(0.0)
    normal = dr.select(hit, prim["n"], V3(0.0))
    depth = _eye_depth(fs, rd, prim["t"], ray.d, hit)
    alb = dr.clip(dr.select(hit, prim["albedo"], mi.Color3f(0.0)), 0.0, 1.0)
    index = _shape_index(fs, rd, prim["shape"], hit)
    spec = [dr.gather(Float, fs.table_specular[c], index) for c in range(3)]
    rough = dr.gather(Float, fs.table_roughness, index)
    motion = _motion(fs, rd, p, ray.d, hit, index)
    if fs.has_defocus:
        k = rd.f
        z = ((p.x - k(K_EYE)) * k(K_FWD) + (p.y - k(K_EYE + 1)) * k(K_FWD + 1)
             + (p.z - k(K_EYE + 2)) * k(K_FWD + 2))
        coc_k = k(K_COC)
        coc = dr.select(hit, dr.select(z > 0, coc_k * (1.0 - k(K_FOCUS) / z), 0.0), coc_k)   # miss: z = inf
        lens = mi.warp.square_to_uniform_disk_concentric(ap)
        lens_u, lens_v = lens.x, lens.y
    else:
        coc = lens_u = lens_v = zero
    time = dr.reinterpret_array(Float, rd.w(_W_T)) if fs.has_motion else zero
    return [normal.x, normal.y, normal.z, depth, alb[0], alb[1], alb[2], *spec, rough, *motion, coc,
            lens_u, lens_v, time]


def _motion(fs: FrameScene, rd: _Reads, p, d, hit, index) -> list:
    """Motion vectors (x, y) in pixels. World point (w=1) on hits, direction (w=0) at infinity on misses,
    projected with this frame's camera and, moved back by the hit object's velocity (per frame), with the
    previous one. No previous position (behind or inside the previous camera's near plane): 0. Vectors
    are capped at MOTION_LIMIT image sizes: beyond that the previous position is far off-screen anyway,
    and an uncapped one near the camera plane can exceed float16's range (the store's features)."""
    mi, dr = fs.mi, fs.dr
    W, H = fs.cfg.res
    w = dr.select(hit, 1.0, 0.0)
    pts = dr.select(hit, p, d)
    vel = mi.Vector3f(*(dr.gather(mi.Float, fs.table_velocity[c], index) for c in range(3)))
    cur_x, cur_y, ok_cur = _project(fs, rd, K_CLIP, pts, w)
    prev_x, prev_y, ok_prev = _project(fs, rd, K_PREV, pts - vel * w, w)
    lim = float(MOTION_LIMIT * max(W, H))
    ok = ok_cur & ok_prev
    mx, my = prev_x - cur_x, prev_y - cur_y
    ok &= dr.isfinite(mx) & dr.isfinite(my)
    return [dr.clip(dr.select(ok, m, 0.0), -lim, lim) for m in (mx, my)]


def _eye_depth(fs: FrameScene, rd: _Reads, t, d, hit):
    """Distance from the eye (pinhole) or lens point to the primary hit (ray distance ``t``, direction
    ``d``), 0 on a miss. Mitsuba starts camera rays on the near plane (t = NEAR / cos to the view axis):
    that is added back."""
    dr = fs.dr
    cos_view = dr.abs(d.x * rd.f(K_VIEW) + d.y * rd.f(K_VIEW + 1) + d.z * rd.f(K_VIEW + 2))
    return dr.select(hit, t + cam_geom.NEAR / dr.maximum(cos_view, 1e-6), 0.0)


def _shape_index(fs: FrameScene, rd: _Reads, sid, hit):
    """Index into the per-shape tables (0 = no hit) of the hit shapes' registry ids."""
    mi, dr = fs.mi, fs.dr
    rel = sid - rd.u(0)                                 # wraps around below the base: out of range
    return dr.gather(mi.UInt32, fs.table_lut, rel, hit & (rel < rd.u(1)))


MISS_DISTANCE = 1e5   # world position of a miss (sample_geometry): this far along its ray, in scene units


def _geometry(fs: FrameScene, seed: int, row0: int, rows: int, s_per: int, t: float) -> dict:
    """The world-space geometry of one wavefront's samples (the rays of :func:`_wave` with the same
    arguments, without shading): ``position`` (float32, N×3: the primary hit; a miss: the point
    :data:`MISS_DISTANCE` along its ray), ``motion`` (float32, N×3: the hit point's position one frame
    earlier minus its position now, ``-velocity``; 0 on a miss) and ``depth`` (float32, N: the
    ``depth`` feature, to check the samples against a store's)."""
    mi, dr = fs.mi, fs.dr
    rd = _Reads(fs, _wave_params(fs, row0, t), rows * fs.cfg.width * s_per)
    _sampler, ray, _weight, _film, _ap = _camera_rays(fs, rd, seed, rows, s_per)
    si = fs.scene.ray_intersect(ray, mi.RayFlags.All, True)
    hit = si.is_valid()
    Float, V3 = mi.Float, mi.Vector3f
    index = _shape_index(fs, rd, dr.reinterpret_array(mi.UInt32, si.shape), hit)
    vel = V3(*(dr.gather(Float, fs.table_velocity[c], index) for c in range(3)))
    pos = dr.select(hit, si.p, ray.o + ray.d * dr.opaque(Float, MISS_DISTANCE))
    motion = dr.select(hit, -vel, V3(0.0))
    depth = _eye_depth(fs, rd, si.t, ray.d, hit)
    dr.eval(pos, motion, depth)
    return {"position": np.asarray(pos, np.float32).T.copy(), "motion": np.asarray(motion, np.float32).T.copy(),
            "depth": np.asarray(depth, np.float32)}


def _project(fs: FrameScene, rd: _Reads, slot: int, p, w):
    """Pixel coordinates (x, y) and validity of world points ``p`` (w = 1) or directions (w = 0) under
    the world-to-clip matrix at ``slot`` of the frame's constants (rows x, y, w; ``scene_gen.projection.
    project_pixels`` in drjit; invalid: behind the camera or nearer than its near plane)."""
    dr = fs.dr
    W, H = fs.cfg.res
    rows = [[rd.f(slot + 4 * r + j) for j in range(4)] for r in range(3)]
    cx, cy, cw = (r[0] * p.x + r[1] * p.y + r[2] * p.z + r[3] * w for r in rows)
    ok = cw > dr.select(w > 0, cam_geom.NEAR, 1e-12)
    cw = dr.select(ok, cw, 1.0)
    return (cx / cw + 1.0) * (0.5 * W), (1.0 - cy / cw) * (0.5 * H), ok


def render_inputs(fs: FrameScene, sample_hook: Callable | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-sample inputs: ``radiance`` (float32, HWS3), ``features`` (float32, HWS17), non-finite count
    (:func:`input_samples` without its guides)."""
    out = input_samples(fs, sample_hook)
    return out["radiance"], out["features"], out["nonfinite"]


def input_samples(fs: FrameScene, sample_hook: Callable | None = None) -> dict:
    """Per-sample inputs and their per-pixel guides: ``radiance`` (float32, HWS3), ``features`` (float32,
    HWS17), ``guides_albedo``/``normal``/``depth``/``motion`` (float32, HWC: sample means) and
    ``nonfinite`` (samples with any non-finite value, before the rule).

    Each wavefront is one kernel (plus one small guide kernel where it completes its pixels) and one
    read-back; the NaN/Inf rule and the guide means run on the device. ``sample_hook(radiance,
    features)`` (float32 N×3, N×17 arrays of one wavefront, modified in place; tests inject values with
    it) runs before the rule, which then runs on the host (:func:`sanitize_samples`), and so do the
    guide means (numpy's mean over the samples; the device's agree within an ulp or two).
    """
    W, H = fs.cfg.res
    S = fs.cfg.spp
    waves = list(_input_wavefronts(fs))
    whole = len(waves) == 1
    shapes = {"radiance": (H, W, S, 3), "features": (H, W, S, NUM_FEATURES),
              **{f"guides_{g}": (H, W, FEATURE_GROUPS[g].stop - FEATURE_GROUPS[g].start) for g in GUIDE_GROUPS}}
    out = {} if whole else {k: np.empty(s, np.float32) for k, s in shapes.items()}   # every element is written
    bad = 0
    for (seed, row0, rows, s_per, t), sl, buf in _launched(fs, waves, sanitize=sample_hook is None):
        part = _read_wave(fs, buf, rows, s_per, complete=sl[2].stop == S)
        if sample_hook is not None:
            sample_hook(part["radiance"], part["features"])
            part["radiance"], part["features"], b = sanitize_samples(part["radiance"], part["features"],
                                                                     fs.cfg.max_value)
            part["nonfinite"] = b
        bad += part.pop("nonfinite", 0)
        for k, a in part.items():
            dst = sl if k in ("radiance", "features") else np.s_[row0:row0 + rows]
            if whole:
                out[k] = a.reshape(shapes[k])
            else:
                out[k][dst] = a.reshape(out[k][dst].shape)
    if sample_hook is not None:
        for g in GUIDE_GROUPS:
            out[f"guides_{g}"] = out["features"][..., FEATURE_GROUPS[g]].mean(axis=2)
    out["nonfinite"] = int(bad)
    return out


def _launched(fs: FrameScene, waves: list, *, sanitize: bool):
    """Launch the wavefronts in order and yield each as ``(args, slice, buffer)`` once the next is
    launched, so reading one overlaps the device's work on the next; at once where the next must move
    the scene first (a new time slice: moving the geometry rebuilds what the pending kernel traces).
    The guide kernel of a chunk of rows follows the wavefront of its last time slice."""
    S = fs.cfg.spp
    earlier = {}                                        # row0 -> guide columns of the chunk's earlier slices
    pending = None
    for args, sl in waves:
        seed, row0, rows, s_per, t = args
        if pending is not None and t != pending[0][4]:
            yield pending
            pending = None
        fs.set_time(t)
        complete = sl[2].stop == S
        buf, cols, _ = _wave(fs, seed, _wave_params(fs, row0, t), rows, s_per, sanitize=sanitize, room=complete)
        earlier.setdefault(row0, []).append(cols)
        if complete:
            _guide_block(fs, buf, rows, s_per, earlier.pop(row0))
        if pending is not None:
            yield pending
        pending = (args, sl, buf)
    if pending is not None:
        yield pending


def _read(buf) -> np.ndarray:
    """The input loop's one device-to-host read (``pipeline.bench_render.kernel_counts`` counts here)."""
    return np.asarray(buf)


def _read_wave(fs: FrameScene, buf, rows: int, s_per: int, *, complete: bool) -> dict:
    """A launched wavefront's buffer, read back once, as views: ``radiance`` (N×3), ``features`` (N×17)
    and, where it completes its pixels, the guides (rows×W×C) and ``nonfinite``."""
    W = fs.cfg.width
    n, P = rows * W * s_per, rows * W
    a = _read(buf).view(np.float32)                     # the one read-back
    part = {"radiance": a[:3 * n].reshape(n, 3), "features": a[3 * n:_SAMPLE_FLOATS * n].reshape(n, NUM_FEATURES)}
    if complete:
        off = _SAMPLE_FLOATS * n
        for g in GUIDE_GROUPS:
            width = FEATURE_GROUPS[g].stop - FEATURE_GROUPS[g].start
            part[f"guides_{g}"] = a[off:off + P * width].reshape(rows, W, width)
            off += P * width
        part["nonfinite"] = int(a[off:off + P].sum(dtype=np.float64))
    return part


def _input_wavefronts(fs: FrameScene):
    """The wavefronts of the input samples, in order: ``((seed, row0, rows, s_per, t), slice)`` with the
    arguments of one :func:`_wave` and the ``(H, W, S)`` slice of the frame they fill. Time slices first
    (samples ``k * s_per ...`` of every pixel at slice time ``t_k``), then row chunks of at most
    ``cfg.max_wavefront`` lanes; each has its own seed."""
    cfg, frame = fs.cfg, fs.frame
    W, H = cfg.res
    slices = math.gcd(cfg.time_slices, cfg.spp) if fs.has_motion else 1
    s_per = cfg.spp // slices
    times = slice_times(time_rng(fs.seed, frame, cfg, 0), slices) if fs.has_motion else np.zeros(1)
    rows_per = max(1, min(H, cfg.max_wavefront // (W * s_per)))
    for k, t in enumerate(times):
        for c, row0 in enumerate(range(0, H, rows_per)):
            rows = min(rows_per, H - row0)
            seed = stream_seed(fs.seed, frame, STREAM_INPUTS, k, c, offset=cfg.seed_offset)
            yield (seed, row0, rows, s_per, float(t)), np.s_[row0:row0 + rows, :, k * s_per:(k + 1) * s_per]


def sample_geometry(fs: FrameScene) -> dict[str, np.ndarray]:
    """The world-space geometry of the frame's input samples, exactly the samples of
    :func:`render_inputs` (the same rays, traced to their first hit, not shaded; a small fraction of
    its time): ``position`` and ``motion`` (float32, H×W×S×3) and ``depth`` (float32, H×W×S). See
    :func:`_geometry`. Used by the ``noisebase`` export, whose format stores them per sample."""
    W, H = fs.cfg.res
    S = fs.cfg.spp
    out = {"position": np.empty((H, W, S, 3), np.float32), "motion": np.empty((H, W, S, 3), np.float32),
           "depth": np.empty((H, W, S), np.float32)}
    for args, sl in _input_wavefronts(fs):
        fs.set_time(args[-1])
        g = _geometry(fs, *args)
        rows, s_per = args[2], args[3]
        for k, a in g.items():
            out[k][sl] = a.reshape(rows, W, s_per, *a.shape[1:])
    fs.set_time(0.0)
    return out


def sanitize_samples(L: np.ndarray, F: np.ndarray, max_value: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Apply the NaN/Inf rule to samples (N×3 radiance, N×17 features); returns (L, F, count). The host
    form of the input kernel's rule (:func:`_sanitize_columns`), sample by sample: a NaN radiance
    component zeroes the sample's radiance, +-Inf radiance becomes +-``max_value``, a non-finite
    feature 0; finite values are kept."""
    if np.isfinite(L).all() and np.isfinite(F).all():
        return L, F, 0                      # the common case, in a tenth of the time of the rule below
    nan_l = np.isnan(L).any(axis=1)
    bad = ~np.isfinite(L).all(axis=1) | ~np.isfinite(F).all(axis=1)
    L = np.where(nan_l[:, None], 0.0, np.where(np.isinf(L), np.copysign(max_value, L), L)).astype(L.dtype)
    F = np.where(np.isfinite(F), F, 0.0).astype(F.dtype)
    return L, F, int(bad.sum())


