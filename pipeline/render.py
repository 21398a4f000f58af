"""The per-sample renderer: one frame of a SceneSpec → the arrays of ``stores.contract``.

``render_frame(spec, frame, cfg) -> dict`` returns every name of ``FRAME_ARRAYS`` (shapes with
H, W = ``cfg.res[1], cfg.res[0]``, S = ``cfg.spp``, L = ``cfg.layer_levels``), ``meta`` (the keys of
``FRAME_META``) and, when ``cfg.oracle_spp > 0``, ``oracle`` (float32, HWC): plain ``mi.render``.

What is rendered (all with the scene's ``path`` integrator: ``spec.max_depth`` bounces, no Russian
roulette, box pixel filter, built by ``scene_gen.to_mitsuba``):

- **Inputs** (``radiance`` float32 HWS3, ``features`` float32 HWS17): one drjit wavefront of
  W·H·S samples (split in row chunks of at most ``cfg.max_wavefront`` lanes). Each sample draws
  its film position uniformly inside its pixel, a lens sample and a wavelength sample from an
  ``independent`` sampler, builds the ray with ``sensor.sample_ray_differential`` and traces it once
  with ``pipeline.primary_path`` (Mitsuba's ``path`` integrator step for step: the same per-sample
  radiance as ``integrator.sample``, times the ray weight), which also hands back the primary hit
  for the features. A pixel's mean is therefore the same estimator as ``mi.render``'s. Each
  wavefront is one drjit kernel that writes its samples, after the NaN/Inf rule, straight into one
  buffer, plus one small kernel for the guides, and one read-back. Features
  (``stores.contract.FEATURE_NAMES``): world shading normal, distance along the ray, diffuse
  albedo (``eval_diffuse_reflectance``, clipped to [0, 1]), specular colour and roughness from the
  hit object's ``MaterialSpec`` (a table keyed by shape), motion, CoC,
  lens position on the unit disk (Mitsuba camera axes: +x left, +y up), time. All 0 on a miss,
  except motion (the environment's motion under the camera change) and CoC (its limit at infinite
  depth, ``A W / (2 F tan(fov/2))``).
- **Sample layers** (``layers`` float32 LHWC): ``mi.render(scene, spp=2**n)`` for n < L, one
  independent seed each.
- **Reference** (``reference``, ``reference_stderr`` float32 HWC), by ``cfg.reference``:

  - ``moments`` (the default): one ``mi.render`` launch a shutter time with the scene's integrator
    wrapped to add each sample's squared R, G, B (:func:`moment_integrator`), so each launch gives every
    pixel's mean and sample variance; the launches are strata of one estimator and the standard error is
    ``sqrt(sum(n_i var_i)) / N`` (:func:`_reference_moments`). A static frame is one launch; a moving
    frame uses ``ref_time_slices`` = :func:`reference_time_count` of its shutter displacement distinct
    times, at most ``ref_max_times`` (16), at the centres of equal strata (``ref_times`` > 0 sets it:
    dense-time checks). ``ref_passes`` is the early stop's granularity: a stop lands on a whole number of
    ``ref_spp / ref_passes`` samples.
  - ``batch_means`` (stores made before ``reference`` existed resume with it): ``cfg.ref_passes`` passes
    of ``ref_spp / ref_passes`` spp, each ``mi.render`` with its own seed at ``ref_time_slices`` times;
    the standard error is the batch-means estimate ``sqrt(var(pass means) / passes)`` (ddof 1).

  With ``ref_target_rel_stderr`` the reference stops once at least ``ref_min_passes`` passes' samples
  are done and the image's relative standard error (below) is under the target;
  ``meta['reference_spp']``, ``meta['reference_rel_stderr']`` and ``meta['ref_time_slices']`` record
  what was achieved. Relative standard error of an image: the mean over pixels of
  ``stderr_Y / (mean_Y + 0.01)``, Y the Rec. 709 luminance.
- **Guides** (float32, HWC): per-pixel means of the input samples' albedo, normal (not
  renormalised), depth and motion; ``camera_to_world`` and ``world_to_clip`` (float64 4x4, see
  ``scene_gen.projection`` for the conventions).

Time, motion blur and motion vectors. Time ``t`` in [0, 1) is the fraction of the shutter: the
scene time is ``tau = frame + spec.shutter * t`` (frames). Mitsuba has no moving geometry inside one
render, so a scene with ``spec.has_motion`` is rendered in time *slices*: the vertex positions of
each moving object are set for the slice's time (``mi.traverse`` + ``update``) and that slice's share
of the samples is rendered. Inputs use ``g = gcd(cfg.time_slices, spp)`` slices with jittered
stratified times ``t_k = (k + u_k) / g`` (samples ``s`` of every pixel in slice ``k = s // (S/g)``,
so samples are ordered by time); each layer likewise with its own jitter (1 spp: one uniform time), with
fewer slices where :func:`reference_time_count` at the layer's samples needs fewer (``moments``);
the reference as above (``batch_means``: ``cfg.ref_time_slices`` times per pass, consecutive blocks of
a randomly shifted van der Corput sequence). The ``time`` feature is the slice time ``t_k``, i.e.
the time the geometry was actually at. A scene without ``has_motion`` renders in one pass at
``tau = frame`` and its ``time`` feature is 0.

Motion vectors (``motion_x``, ``motion_y``, pixels): ``p_prev - p_cur``, where ``p_cur`` is the
pinhole projection of the sample's primary hit point ``x`` with this frame's camera, and ``p_prev``
the projection of the same surface point one frame earlier (``x - velocity`` of the hit object,
velocity in world units per frame) with the previous frame's camera. Rule for the first frame of a
clip and for stills: the previous camera is the frame's own camera (the camera is taken to be at
rest before the clip) and objects still move back by one frame. Environment hits project the ray
direction (a point at infinity). Points behind the previous camera, or nearer than its near plane, get
motion 0, and vectors are capped at ``MOTION_LIMIT`` (16) image sizes (so they fit float16). Motion vectors do
not follow reflections or refraction (they describe the primary hit). They are computed for every
scene (cheap); without moving objects or cameras they are exactly 0.

Circle of confusion (``coc``): signed radius in pixels, ``scene_gen.projection.coc_pixels`` (0 at the
focus distance, + behind focus, - in front); 0 everywhere without defocus (no lens sampling:
``lens_u = lens_v = 0``).

NaN and Inf rule (counted in ``meta``, never written silently):
- inputs: a sample whose radiance has a NaN gets radiance 0; +-Inf radiance components are clamped
  to +-``cfg.max_value`` (1e8); non-finite features are set to 0. ``nonfinite_inputs`` counts the
  samples with any non-finite radiance or feature value.
- layers: ``mi.render`` only returns pixel means, so a pixel with a NaN becomes 0 and Inf is
  clamped; ``nonfinite_layers`` counts such pixels over all layers.
- reference: a launch's (``batch_means``: a pass's) NaN pixel is left out of that pixel (the pixel keeps
  its other launches), Inf is clamped (``moments``: its variance taken as ``max_value**2``);
  ``nonfinite_reference`` counts such pixel-launches.

Seeds: every sampler seed is ``stream_seed(spec.seed, frame, stream, *index, cfg.seed_offset)``
from ``np.random.SeedSequence``: inputs, each layer, each reference pass, time jitter and the oracle
are distinct streams, so no two renders share a seed and the same (spec, frame, cfg) gives identical
bytes (up to ``meta['render_seconds']``).
"""
from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from scene_gen import projection as cam_geom
from pipeline.errors import ConfigError, RenderError
from core.checks import is_int, is_number, known_keys, need, need_int
from scene_gen.spec import SceneSpec
from stores.contract import FEATURE_GROUPS, FRAME_ARRAYS, FRAME_META, NUM_FEATURES

# Sampler streams (the third entry of every seed's SeedSequence).
STREAM_INPUTS, STREAM_LAYER, STREAM_REFERENCE, STREAM_ORACLE, STREAM_TIME = 1, 2, 3, 4, 5
LUMA = np.array([0.2126, 0.7152, 0.0722])
# ``moments`` (the default): per-sample second moments inside each launch, shutter times by the frame's
# motion (:func:`reference_time_count`). ``batch_means``: ``ref_passes`` passes of ``ref_time_slices``
# times each and the batch-means error (the method of stores made before ``reference`` existed).
REFERENCE_METHODS = ("moments", "batch_means")
# The motion rule's bound: rms banding at a moving edge over the reference's own noise there.
BANDING_OVER_NOISE = 0.5
REL_STDERR_EPS = 0.01


@dataclass(frozen=True)
class RenderConfig:
    """How to render a frame. Validated at construction (the message names the field and range)."""
    res: tuple[int, int] = (256, 256)        # (W, H) in pixels; an int means square
    spp: int = 8                             # input samples per pixel (S)
    layer_levels: int = 6                    # sample layers of 1, 2, 4, ... 2**(L-1) spp
    ref_spp: int = 4096                      # reference samples per pixel (at most; 0 = no reference)
    ref_passes: int = 32                     # batch means: ref_spp is split into this many passes
    ref_min_passes: int = 16                 # passes before an early stop may happen
    ref_target_rel_stderr: float | None = None   # early stop once the relative standard error is below
    time_slices: int = 4                     # time slices per render for scenes with moving objects
    ref_time_slices: int = 4                 # batch_means only: time slices per reference pass
    reference: str = "moments"               # how the reference and its error are made (REFERENCE_METHODS)
    ref_max_times: int = 16                  # moments: at most this many distinct shutter times a frame
    ref_times: int = 0                       # moments: > 0 sets a moving frame's times (dense checks)
    threads: int = 0                         # drjit threads (0 = leave as is)
    seed_offset: int = 0                     # extra SeedSequence entropy (0 = the dataset default)
    max_value: float = 1e8                   # +-Inf radiance is clamped to this
    oracle_spp: int = 0                      # > 0: also render plain mi.render at this spp ('oracle')
    max_wavefront: int = 1 << 21             # lanes per drjit wavefront of the input loop

    def __post_init__(self):
        res = self.res
        if is_int(res):
            res = (res, res)
        need(isinstance(res, (tuple, list)) and len(res) == 2 and all(is_int(r) and r > 0 for r in res),
             "render.res", "a positive int or (W, H) of positive ints", self.res, ConfigError)
        object.__setattr__(self, "res", (int(res[0]), int(res[1])))
        need_int("render.spp", self.spp, 1, 4096, ConfigError)
        need_int("render.layer_levels", self.layer_levels, 0, 12, ConfigError)
        need_int("render.ref_passes", self.ref_passes, 2, 65536, ConfigError)
        need(is_int(self.ref_spp) and (self.ref_spp == 0 or (self.ref_spp >= self.ref_passes
                                                              and self.ref_spp % self.ref_passes == 0)),
             "render.ref_spp", f"0 or a positive multiple of ref_passes ({self.ref_passes})", self.ref_spp,
             ConfigError)
        need(is_int(self.ref_min_passes) and 2 <= self.ref_min_passes <= self.ref_passes, "render.ref_min_passes",
             f"an integer in [2, ref_passes={self.ref_passes}]", self.ref_min_passes, ConfigError)
        t = self.ref_target_rel_stderr
        need(t is None or (is_number(t, finite=True) and t > 0), "render.ref_target_rel_stderr",
             "None or a number > 0", t, ConfigError)
        need_int("render.time_slices", self.time_slices, 1, 1024, ConfigError)
        s = self.ref_time_slices
        need(is_int(s) and s >= 1 and s & (s - 1) == 0, "render.ref_time_slices", "a power of two >= 1", s,
             ConfigError)
        need(self.reference in REFERENCE_METHODS, "render.reference", f"one of {', '.join(REFERENCE_METHODS)}",
             self.reference, ConfigError)
        s = self.ref_max_times
        need(is_int(s) and 1 <= s <= 1024 and s & (s - 1) == 0, "render.ref_max_times",
             "a power of two in [1, 1024]", s, ConfigError)
        need_int("render.ref_times", self.ref_times, 0, 65536, ConfigError)
        if self.ref_times and self.ref_spp:
            half = self.ref_spp // self.ref_passes // 2
            need(half >= 1 and half % self.ref_times == 0, "render.ref_times",
                 f"0 or a divisor of half a pass's samples (ref_spp / ref_passes / 2 = {half})", self.ref_times,
                 ConfigError)
        need(is_int(self.threads) and 0 <= self.threads <= 1024, "render.threads",
             "an integer in [0, 1024] (0 = default)", self.threads, ConfigError)
        need_int("render.seed_offset", self.seed_offset, 0, None, ConfigError)
        need(is_number(self.max_value, finite=True) and self.max_value > 0, "render.max_value",
             "a finite number > 0", self.max_value, ConfigError)
        need_int("render.oracle_spp", self.oracle_spp, 0, None, ConfigError)
        need_int("render.max_wavefront", self.max_wavefront, 1024, None, ConfigError)

    @property
    def width(self) -> int:
        return self.res[0]

    @property
    def height(self) -> int:
        return self.res[1]

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["res"] = list(self.res)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RenderConfig":
        d = known_keys(d, cls, "render", ConfigError, noun="field(s)")
        if isinstance(d.get("res"), list):
            d["res"] = tuple(d["res"])
        return cls(**d)


def stream_seed(scene_seed: int, frame: int, stream: int, *index: int, offset: int = 0) -> int:
    """A sampler seed in [0, 2**31) for one stream of one frame (``np.random.SeedSequence``)."""
    ss = np.random.SeedSequence([int(scene_seed), int(frame), int(stream), *map(int, index), int(offset)])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)


def _rng(seed: int, frame: int, cfg: RenderConfig, *index: int) -> np.random.Generator:
    """The time-jitter stream of a scene ``seed``'s frame (``STREAM_TIME``)."""
    return np.random.default_rng(np.random.SeedSequence(
        [int(seed), int(frame), STREAM_TIME, *map(int, index), int(cfg.seed_offset)]))


def _van_der_corput(n: int) -> np.ndarray:
    out = np.zeros(n)
    for i in range(n):
        f, x, k = 0.5, 0.0, i
        while k:
            x += f * (k & 1)
            k >>= 1
            f *= 0.5
        out[i] = x
    return out


def reference_time_count(displacement: float, spp: int, cap: int) -> int:
    """Distinct shutter times a render of ``spp`` samples a pixel needs for a frame whose moving vertices
    travel at most ``displacement`` pixels during the shutter: the least power of two ``T`` (at most
    ``cap``; 1 for ``displacement`` 0) whose banding at a moving edge stays below
    :data:`BANDING_OVER_NOISE` times the render's own noise there.

    The derivation (docs/throughput.md, "Shutter times by motion"): with the box pixel filter, a pixel
    that an edge of contrast ``c`` crosses sees a ramp of slope ``c d`` over the shutter (``d`` the
    displacement). ``T`` times at the centres of equal strata (the midpoint rule) miss each of its two
    kinks by ``c d / (T^2 sqrt(320))`` rms, ``c d / (12.65 T^2)`` for both. The render's noise at that
    pixel is at least the coverage noise of its samples, ``c / sqrt(6 max(d, 1) N)`` for ``N`` samples.
    Banding over noise at most ``r``: ``T^2 >= d sqrt(6 max(d, 1) N) / (12.65 r)``; at ``N`` = 1024 and
    ``r`` = 1/2, ``T >= 3.52 d^(3/4)`` for ``d >= 1`` (``d`` = 1: 4; 4: 16; 8: 32 before the cap)."""
    d = float(displacement)
    if not d > 0.0:
        return 1
    if not math.isfinite(d):
        t = math.inf
    else:
        t = math.sqrt(d * math.sqrt(6.0 * max(d, 1.0) * max(int(spp), 1)) / (math.sqrt(160.0) * BANDING_OVER_NOISE))
    n = 1
    while n < t and n < cap:
        n *= 2
    return min(n, int(cap))


def slice_times(rng: np.random.Generator, slices: int) -> np.ndarray:
    """Jittered stratified times in [0, 1) (float64, ``slices``): ``(k + u_k) / slices``."""
    return np.minimum((np.arange(slices) + rng.random(slices)) / slices, np.nextafter(1.0, 0.0))


class FrameScene:
    """A loaded Mitsuba scene of one frame plus what the renderer needs around it.

    ``set_time(t)`` moves the moving objects to ``tau = frame + shutter * t``; the per-shape tables
    (index 0 = no hit) hold specular colour (float64, N×3), roughness (N) and velocity (N×3).
    ``merge`` (default): identical materials share a BSDF and static objects sharing a material are
    one mesh (``scene_gen.to_mitsuba.shape_groups``): the same image distribution as the unmerged
    scene, faster (``make bench``, each scene alone in its process: 1.1x on indoor seed 0 at 128x128).
    Only one FrameScene should be alive per process while rendering: drjit traces a virtual call for
    every instance alive, so a second scene grows every kernel (``pipeline.tasks``).
    """

    def __init__(self, spec: SceneSpec, frame: int, cfg: RenderConfig,
                 on_scene_loaded: Callable | None = None, *, merge: bool = True):
        from core.variant import mitsuba
        from scene_gen import to_mitsuba

        self.mi = mi = mitsuba(threads=cfg.threads or None)
        import drjit as dr
        self.dr = dr
        self.frame, self.cfg = int(frame), cfg
        # the one call from spec to scene: nothing below reads the spec
        self.loaded = ld = to_mitsuba.load_frame(spec, frame, cfg.res, merge=merge, on_loaded=on_scene_loaded)
        self.scene, self.cam, self.prev_cam = ld.scene, ld.camera, ld.prev_camera
        self.seed, self.num_frames, self.case, self.kind = ld.seed, ld.num_frames, ld.case, ld.kind
        self.merged = bool(merge)
        self.sensor = self.scene.sensors()[0]
        self.integrator = self.scene.integrator()
        self.sampler = mi.load_dict({"type": "independent"})
        self.has_motion, self.has_defocus = ld.has_motion, ld.has_defocus
        self.displacement = ld.shutter_displacement()       # pixels a moving vertex travels in the shutter
        self._moments = None
        self.camera_to_world = ld.camera_to_world
        self.view_axis = self.camera_to_world[:3, 2]
        self.world_to_clip, self.prev_world_to_clip = ld.world_to_clip, ld.prev_world_to_clip
        self._check_sensor()
        lut_size = self._shape_tables()
        self.consts, self.consts_u = self._input_constants(lut_size)
        self.integrator_depths = self._path_depths()

    def _shape_tables(self) -> int:
        """The per-shape tables (index 0 = no hit; a merged shape's objects share one material and are
        static) in numpy and on the drjit side, where the input kernel looks them up by registry id -
        ``lut_base``. Returns the size of that lookup table."""
        mi, dr = self.mi, self.dr
        shapes = self.scene.shapes()
        ids = np.asarray(dr.reinterpret_array(mi.UInt32, self.scene.shapes_dr()), np.int64).ravel()
        if len(ids) != len(shapes):
            raise RenderError("scene.shapes() and scene.shapes_dr() disagree")
        self._order = np.argsort(ids)
        self._sorted_ids = ids[self._order]
        # per-shape tables; a merged shape's objects share one material and are static
        members = self.loaded.shapes
        n = len(shapes) + 1
        self.specular = np.zeros((n, 3))
        self.roughness = np.zeros(n)
        self.velocity = np.zeros((n, 3))
        for i, s in enumerate(shapes):
            objs = members.get(s.id())
            if not objs:
                continue
            o = objs[0]
            self.specular[i + 1] = o.material.specular_color
            self.roughness[i + 1] = o.material.roughness
            if o.velocity is not None:
                self.velocity[i + 1] = o.velocity
        # the same tables on the drjit side, looked up in the input kernel by registry id - lut_base
        self.lut_base = int(ids.min()) if len(ids) else 0
        lut = np.zeros(int(ids.max()) - self.lut_base + 1 if len(ids) else 1, np.uint32)
        lut[ids - self.lut_base] = np.arange(1, len(ids) + 1, dtype=np.uint32)
        self.table_lut = mi.UInt32(lut)
        self.table_specular = [mi.Float(self.specular[:, c].astype(np.float32)) for c in range(3)]
        self.table_roughness = mi.Float(self.roughness.astype(np.float32))
        self.table_velocity = [mi.Float(self.velocity[:, c].astype(np.float32)) for c in range(3)]
        return len(lut)

    def _input_constants(self, lut_size: int):
        """The per-frame constants of the input kernel, uploaded once (the kernel gathers them at the
        fixed slots ``_K_*``, so one compiled kernel serves every frame): a Float array (the two
        world-to-clip matrices' rows x, y, w, the view axis, and for defocus the camera's origin and
        forward axis, the CoC factor and the focus distance) and a UInt32 array (shape-table base, size)."""
        cam = self.cam
        o, f = self.camera_to_world[:3, 3], self.camera_to_world[:3, 2]
        k = (cam.aperture_radius * self.cfg.width / (2.0 * cam.focus_distance * cam_geom.tan_half_fov_x(cam))
             if self.has_defocus else 0.0)
        vals = np.concatenate([self.world_to_clip[[0, 1, 3]].ravel(), self.prev_world_to_clip[[0, 1, 3]].ravel(),
                               self.view_axis, o, f, [k, cam.focus_distance if self.has_defocus else 0.0]])
        assert len(vals) == _K_SIZE
        return self.mi.Float(vals.astype(np.float32)), self.mi.UInt32(np.array([self.lut_base, lut_size], np.uint32))

    def _path_depths(self) -> tuple[int, int]:
        """(max_depth, rr_depth) of the scene's ``path`` integrator, which the input loop's own path tracer
        (``pipeline.primary_path``) follows; ``scene_gen.to_mitsuba.integrator_dict`` is their one source."""
        d = self.loaded.integrator
        text = str(self.integrator)
        if (d["type"] != "path" or d.get("hide_emitters") or "PathIntegrator" not in text
                or f"max_depth = {d['max_depth']}," not in text or f"rr_depth = {d['rr_depth']}" not in text):
            raise RenderError(f"the scene's integrator is not the path integrator of {d}: {text!r}")
        return int(d["max_depth"]), int(d["rr_depth"])

    def _check_sensor(self):
        m = np.array(self.sensor.world_transform().matrix, np.float64).reshape(4, 4)
        if not np.allclose(m, self.camera_to_world, atol=1e-4 * max(1.0, np.abs(self.camera_to_world).max())):
            raise RenderError("the Mitsuba sensor's to_world differs from scene_gen.projection.camera_to_world: "
                              "scene_gen.to_mitsuba and scene_gen.projection disagree on camera conventions")
        x_fov = float(np.ravel(self.mi.traverse(self.sensor)["x_fov"])[0])
        if abs(x_fov - self.cam.fov) > 1e-3:
            raise RenderError(f"sensor x_fov {x_fov} differs from camera.fov {self.cam.fov} (fov_axis must be 'x')")

    def tau(self, t) -> np.ndarray | float:
        """Scene time in frames of shutter fraction(s) ``t``."""
        return self.loaded.tau(t)

    def set_time(self, t: float) -> None:
        """Put the moving objects where they are at shutter fraction ``t`` (no-op without motion)."""
        self.loaded.set_time(t)

    @property
    def ref_time_slices(self) -> int:
        """Distinct shutter times of this frame's reference: :func:`reference_time_count` of its motion
        (``moments``), ``ref_time_slices`` a pass (``batch_means``); 1 without motion or reference."""
        cfg = self.cfg
        if not self.has_motion or cfg.ref_spp == 0:
            return 1
        pass_spp = cfg.ref_spp // cfg.ref_passes
        if cfg.reference == "batch_means":
            return math.gcd(cfg.ref_time_slices, pass_spp)
        if cfg.ref_times:
            return cfg.ref_times
        # a power of two that leaves every launch of a pass at least 2 samples (its variance)
        return math.gcd(reference_time_count(self.displacement, cfg.ref_spp, cfg.ref_max_times),
                        max(1, pass_spp // 2))

    def slices_for(self, spp: int) -> int:
        """Time slices of a layer render of ``spp`` samples a pixel (:func:`render_sliced`; the inputs keep
        ``time_slices``): :func:`reference_time_count` of the frame's motion at those samples, at most
        ``time_slices`` (``moments``; ``batch_means``: ``time_slices``), a divisor of ``spp``; 1 without
        motion."""
        if not self.has_motion:
            return 1
        cap = self.cfg.time_slices
        if self.cfg.reference == "moments":
            cap = reference_time_count(self.displacement, spp, cap)
        return math.gcd(cap, spp)

    @property
    def moment_integrator(self):
        """The scene's integrator wrapped to add each pixel's second moment (``moments``; built once)."""
        if self._moments is None:
            self._moments = moment_integrator(self.mi, self.integrator)
        return self._moments

    def shape_index(self, registry_ids: np.ndarray) -> np.ndarray:
        """Table index (int64, 0 = no hit) of drjit shape registry ids (0 = no hit)."""
        ids = np.asarray(registry_ids, np.int64)
        if len(self._sorted_ids) == 0:
            return np.zeros(ids.shape, np.int64)
        pos = np.clip(np.searchsorted(self._sorted_ids, ids), 0, len(self._sorted_ids) - 1)
        found = (self._sorted_ids[pos] == ids) & (ids != 0)
        return np.where(found, self._order[pos] + 1, 0)


# ------------------------------------------------------------------------------------------------
# inputs
# Slots of FrameScene.consts (Float: world-to-clip rows x, y, w of this and the previous frame, view axis,
# lens-camera origin and forward axis, CoC factor, focus distance) and of a wavefront's parameters (UInt32;
# the two times by their float32 bits). Values reach the kernel through memory, so one compiled kernel
# serves every wavefront, slice and frame, at one upload a wavefront.
_K_CLIP, _K_PREV, _K_VIEW, _K_EYE, _K_FWD, _K_COC, _K_FOCUS, _K_SIZE = 0, 12, 24, 27, 30, 33, 34, 35
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
    film = (mi.Point2f(px, py) + sampler.next_2d()) * mi.ScalarPoint2f(1.0 / W, 1.0 / H)
    ap = sampler.next_2d()
    wav = sampler.next_1d()
    ray, weight = fs.sensor.sample_ray_differential(dr.reinterpret_array(mi.Float, rd.w(_W_TAU)), wav, film, ap)
    return sampler, ray, weight, film, ap


def _wave(fs: FrameScene, seed: int, wp, rows: int, s_per: int, *, sanitize: bool = True, room: bool = False,
          debug: bool = False):
    """Launch one wavefront (asynchronously; nothing is read here): ``rows`` pixel rows, ``s_per``
    samples a pixel. One drjit kernel traces the camera rays once (:mod:`pipeline.primary_path`: the
    radiance and the primary hit together), computes the 17 features, applies the NaN/Inf rule (unless
    ``sanitize`` is false: the tests' ``sample_hook`` path applies it on the host) and writes the 20
    floats of each sample straight into one buffer: radiance (N×3), then features (N×17), lane-major,
    then, with ``room``, space for the guide block (:func:`_guide_block`). Returns ``(buffer, columns,
    extra)``: ``columns`` the guide features and the non-finite flag of every lane (10 Floats, for
    :func:`_guide_block`), ``extra`` the debug fields of :func:`_trace`."""
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
    extra = (dict(p=prim["p"], d=ray.d, film=film, hit=prim["hit"], sid=prim["shape"], n=prim["n"], t=prim["t"],
                  albedo=prim["albedo"], lens=mi.warp.square_to_uniform_disk_concentric(ap)) if debug else {})
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


def _trace(fs: FrameScene, seed: int, row0: int, rows: int, s_per: int, t: float, *, debug: bool = False) -> dict:
    """One wavefront, read back: ``rows`` pixel rows from ``row0``, ``s_per`` samples a pixel, at shutter
    time ``t`` (the scene already there). Returns numpy arrays of N = rows·W·s_per lanes (pixel-major,
    then sample): ``L`` (float32, N×3, radiance times the ray weight) and ``F`` (float32, N×17, the
    features), both after the NaN/Inf rule. ``debug`` (tests): also the primary hit point ``p``, ray
    direction ``d``, film position ``film`` (in [0, 1]²), ``hit``, the hit shape's registry id ``sid``,
    shading normal ``n``, ray distance ``t``, diffuse reflectance ``albedo`` and lens sample on the unit
    disk ``lens``."""
    n = rows * fs.cfg.width * s_per
    buf, _cols, extra = _wave(fs, seed, _wave_params(fs, row0, t), rows, s_per, debug=debug)
    a = _read(buf).view(np.float32)
    out = {"L": a[:3 * n].reshape(n, 3), "F": a[3 * n:].reshape(n, NUM_FEATURES)}
    for k, v in extra.items():
        a = np.asarray(v)
        out[k] = a.T if a.ndim == 2 and a.shape[0] in (2, 3) and a.shape[1] == n else a
    return out


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
        z = ((p.x - k(_K_EYE)) * k(_K_FWD) + (p.y - k(_K_EYE + 1)) * k(_K_FWD + 1)
             + (p.z - k(_K_EYE + 2)) * k(_K_FWD + 2))
        coc_k = k(_K_COC)
        coc = dr.select(hit, dr.select(z > 0, coc_k * (1.0 - k(_K_FOCUS) / z), 0.0), coc_k)   # miss: z = inf
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
    cur_x, cur_y, ok_cur = _project(fs, rd, _K_CLIP, pts, w)
    prev_x, prev_y, ok_prev = _project(fs, rd, _K_PREV, pts - vel * w, w)
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
    cos_view = dr.abs(d.x * rd.f(_K_VIEW) + d.y * rd.f(_K_VIEW + 1) + d.z * rd.f(_K_VIEW + 2))
    return dr.select(hit, t + cam_geom.NEAR / dr.maximum(cos_view, 1e-6), 0.0)


def _shape_index(fs: FrameScene, rd: _Reads, sid, hit):
    """Index into the per-shape tables (0 = no hit) of the hit shapes' registry ids."""
    mi, dr = fs.mi, fs.dr
    rel = sid - rd.u(0)                                 # wraps around below the base: out of range
    return dr.gather(mi.UInt32, fs.table_lut, rel, hit & (rel < rd.u(1)))


MISS_DISTANCE = 1e5   # world position of a miss (sample_geometry): this far along its ray, in scene units


def _geometry(fs: FrameScene, seed: int, row0: int, rows: int, s_per: int, t: float) -> dict:
    """The world-space geometry of one wavefront's samples (the rays of :func:`_trace` with the same
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
    W, S = fs.cfg.width, fs.cfg.spp
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
    arguments of :func:`_trace` and the ``(H, W, S)`` slice of the frame they fill. Time slices first
    (samples ``k * s_per ...`` of every pixel at slice time ``t_k``), then row chunks of at most
    ``cfg.max_wavefront`` lanes; each has its own seed."""
    cfg, frame = fs.cfg, fs.frame
    W, H = cfg.res
    slices = math.gcd(cfg.time_slices, cfg.spp) if fs.has_motion else 1
    s_per = cfg.spp // slices
    times = slice_times(_rng(fs.seed, frame, cfg, 0), slices) if fs.has_motion else np.zeros(1)
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


def _sanitize_image(img: np.ndarray, max_value: float) -> tuple[np.ndarray, int]:
    """NaN pixel → 0, Inf → clamp; returns (image, number of pixels touched)."""
    bad = ~np.isfinite(img).all(axis=-1)
    n = int(bad.sum())
    if n:
        img = np.where(np.isnan(img).any(axis=-1, keepdims=True), 0.0, img)
        img = np.clip(img, -max_value, max_value)
    return img, n


# drjit's arrays hold at most 2**32 - 1 entries (32-bit sizes; drjit-core issue 33), and Mitsuba renders
# all of a call's samples as one wavefront: a 1920x1080 pass of 4096 spp (8.5e9 samples) cannot be one
# launch. Memory is not the limit: the render loop is symbolic (its state lives in registers) and the
# film accumulates by scatter, so a launch's memory grows with its pixels, not its samples.
MAX_LAUNCH_SAMPLES = (1 << 32) - 1


def launch_plan(pixels: int, spp: int, limit: int | None = None) -> list[int]:
    """The spp of each ``mi.render`` launch that renders ``spp`` samples of ``pixels`` pixels: one launch
    where ``pixels * spp`` fits ``limit`` (default :data:`MAX_LAUNCH_SAMPLES`), else the fewest that each
    fit, the samples split as evenly as possible."""
    limit = MAX_LAUNCH_SAMPLES if limit is None else limit
    per = limit // pixels
    if per < 1:
        raise ValueError(f"one sample of each of {pixels} pixels exceeds {limit} samples a launch")
    n = -(-spp // per)
    base, extra = divmod(spp, n)
    return [base + (i < extra) for i in range(n)]


def launch_seed(seed: int, i: int) -> int:
    """The seed of launch ``i`` of a split render: ``seed`` itself for the first (an unsplit render is
    unchanged), independent 31-bit seeds for the others."""
    return int(seed) if i == 0 else int(np.random.SeedSequence([int(seed), i]).generate_state(1)[0] >> 1)


def moment_integrator(mi, nested):
    """``nested`` (a ``SamplingIntegrator``) wrapped to add four AOVs: the square of each sample's R, G
    and B, and 1 for a sample with a NaN (whose value is then 0). The film's box filter averages them
    per pixel, so ``mi.render`` returns each pixel's mean, second moment and share of NaN samples in one
    launch (:data:`MOMENT_CHANNELS`: R, G, B, R², G², B², NaN share; :func:`valid_moments`). Mitsuba's
    own ``moment`` integrator records the second moment of XYZ, from which per-channel RGB variances
    cannot be had, and a film with AOVs sets a NaN sample to 0 without a word, hence the NaN share. The
    wrapper draws nothing itself: the samples are the nested integrator's, and the first three channels
    equal its render to float rounding where no sample is NaN."""
    cls = _MOMENT_CLASSES.get(mi.variant())
    if cls is None:
        class RGBMoments(mi.SamplingIntegrator):
            def __init__(self, inner):
                super().__init__(mi.Properties())
                self.inner = inner

            def sample(self, scene, sampler, ray, medium=None, active=True):
                import drjit as dr
                spec, valid, _ = self.inner.sample(scene, sampler, ray, medium, active)
                c = mi.Color3f(spec)
                nan = dr.isnan(c.x) | dr.isnan(c.y) | dr.isnan(c.z)
                c = dr.select(nan, 0.0, c)
                return c, valid, [c.x * c.x, c.y * c.y, c.z * c.z, dr.select(nan, 1.0, 0.0)]

            def aov_names(self):
                return ["m2.R", "m2.G", "m2.B", "nan"]

            def to_string(self):
                return f"RGBMoments[{self.inner}]"
        cls = _MOMENT_CLASSES[mi.variant()] = RGBMoments
    return cls(nested)


_MOMENT_CLASSES: dict = {}
MOMENT_CHANNELS = 7


def valid_moments(img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and second moment of each pixel's samples that were not NaN (HWC each), and the share of its
    samples that were (HW1), from a :func:`moment_integrator` render (HW x :data:`MOMENT_CHANNELS`): the
    NaN samples entered as 0, so the rest weigh ``1 / (1 - share)``. A pixel of NaN samples only is 0."""
    f = np.clip(img[..., 6:7], 0.0, 1.0)
    keep = np.where(f < 1.0, 1.0 / np.maximum(1.0 - f, 1e-300), 0.0)
    return img[..., :3] * keep, img[..., 3:6] * keep, f


def _mi_render(fs: FrameScene, spp: int, seed: int, *, integrator=None, channels: int = 3) -> np.ndarray:
    """``mi.render`` of ``spp`` samples (float64 HW x ``channels``), in as many launches as :func:`launch_plan`
    says, weighted by their samples; ``integrator`` in place of the scene's own."""
    W, H = fs.cfg.res
    plan = launch_plan(W * H, int(spp))
    acc = 0.0
    for i, n in enumerate(plan):
        img = fs.mi.render(fs.scene, integrator=integrator, spp=int(n), seed=launch_seed(seed, i))
        if fs.scene.integrator().should_stop():
            # Mitsuba's SIGINT handler cancelled this render: what it returned may hold fewer samples than
            # asked for. Fail the task (it is retried) rather than store a frame that is not what it says.
            from pipeline.errors import RenderError
            raise RenderError(f"the render of {spp} spp (seed {seed}) was cancelled by an interrupt signal "
                              "before it finished; its result is not used")
        part = np.asarray(img, np.float64)[..., :channels]
        if len(plan) == 1:
            return part
        acc = acc + part * (n / spp)
    return acc


def render_sliced(fs: FrameScene, spp: int, stream: int, index: int, max_slices: int | None = None, *,
                  integrator=None, channels: int = 3) -> np.ndarray:
    """Plain ``mi.render`` mean (float64, HWC) of ``spp`` samples, time-sliced when the scene moves
    (:meth:`FrameScene.slices_for`, or ``max_slices``); ``integrator`` in place of the scene's own."""
    cfg = fs.cfg
    slices = (math.gcd(max_slices, spp) if max_slices else fs.slices_for(spp)) if fs.has_motion else 1
    times = slice_times(_rng(fs.seed, fs.frame, cfg, stream, index), slices) if fs.has_motion else np.zeros(1)
    acc = 0.0
    for k, t in enumerate(times):
        fs.set_time(float(t))
        acc = acc + _mi_render(fs, spp // slices, stream_seed(fs.seed, fs.frame, stream, index, k,
                                                                offset=cfg.seed_offset),
                               integrator=integrator, channels=channels)
    return acc / slices


def render_layers(fs: FrameScene) -> tuple[np.ndarray, int]:
    """Sample layers (float32, LHWC): layer n is the mean of 2**n independent samples; non-finite count."""
    W, H = fs.cfg.res
    out = np.zeros((fs.cfg.layer_levels, H, W, 3), np.float32)
    # the reference's kernel (one compilation a scene for both); batch_means renders as it always did
    integrator = fs.moment_integrator if fs.cfg.reference == "moments" and fs.cfg.ref_spp else None
    bad = 0
    for lvl in range(fs.cfg.layer_levels):
        img = render_sliced(fs, 2 ** lvl, STREAM_LAYER, lvl, integrator=integrator,
                            channels=MOMENT_CHANNELS if integrator else 3)
        nan = np.zeros(img.shape[:2], bool)
        if integrator is not None:          # the mean of the pixel's samples that were not NaN
            img, _, f = valid_moments(img)
            nan = f[..., 0] > 0
        bad += int((nan | ~np.isfinite(img).all(axis=-1)).sum())     # a NaN sample, or Inf in the mean
        out[lvl] = _sanitize_image(img, fs.cfg.max_value)[0]
    return out, bad


def rel_stderr(mean: np.ndarray, stderr: np.ndarray) -> float:
    """Mean over pixels of ``stderr_Y / (mean_Y + 0.01)`` (Y: Rec. 709 luminance); HWC inputs."""
    y = np.abs(mean @ LUMA)
    e = stderr @ LUMA
    return float(np.mean(e / (y + REL_STDERR_EPS))) if y.size else 0.0


def render_reference(fs: FrameScene) -> dict:
    """The frame's reference: ``reference`` and ``reference_stderr`` (float64, HWC), ``reference_spp``
    (samples taken), ``reference_rel_stderr``, ``nonfinite_reference`` and ``ref_time_slices`` (distinct
    shutter times), by ``cfg.reference``."""
    cfg = fs.cfg
    W, H = cfg.res
    if cfg.ref_spp == 0:
        z = np.zeros((H, W, 3))
        return _reference(z, z.copy(), 0, 0, 1)
    if cfg.reference == "batch_means":
        return _reference_batch_means(fs)
    return _reference_moments(fs)


def _reference(mean, stderr, spp: int, bad: int, times: int) -> dict:
    return {"reference": mean, "reference_stderr": stderr, "reference_spp": int(spp),
            "reference_rel_stderr": rel_stderr(mean, stderr) if spp else 0.0, "nonfinite_reference": int(bad),
            "ref_time_slices": int(times)}


def reference_times(times: int) -> np.ndarray:
    """Shutter fractions of a ``moments`` reference with ``times`` distinct times: the centres of equal
    strata (the midpoint rule of :func:`reference_time_count`'s derivation)."""
    return (np.arange(times) + 0.5) / times


def _reference_moments(fs: FrameScene) -> dict:
    """``moments``: each launch renders one shutter time with the moment integrator, so every launch
    gives each pixel's mean and sample variance. The launches are strata of one estimator: the mean
    weighs each by its samples, and its variance is ``sum(n_i var_i) / N^2`` (``N`` samples in all), an
    unbiased estimate with ``N - launches`` degrees of freedom. A launch's NaN pixel is left out of that
    pixel (counted); ``+-Inf`` is clamped to ``max_value`` and its variance taken as ``max_value^2``.

    Without ``ref_target_rel_stderr`` the reference is one round: one launch a time. With it, a first
    round of ``ref_min_passes`` passes' samples, then rounds predicted from the measured error (it falls
    as 1/sqrt(samples)) until the target or ``ref_spp``; a stop lands on a whole number of passes."""
    cfg = fs.cfg
    W, H = cfg.res
    pass_spp = cfg.ref_spp // cfg.ref_passes
    T = fs.ref_time_slices
    times = reference_times(T) if fs.has_motion else np.zeros(1)
    acc = {"A": np.zeros((H, W, 3)), "B": np.zeros((H, W, 3)), "N": np.zeros((H, W, 1)), "bad": 0}
    target = cfg.ref_target_rel_stderr
    done, want, rnd = 0, (cfg.ref_min_passes if target is not None else cfg.ref_passes), 0
    while True:
        n = (want - done) * pass_spp // T
        for k, t in enumerate(times):
            fs.set_time(float(t))
            img = _mi_render(fs, n, stream_seed(fs.seed, fs.frame, STREAM_REFERENCE, rnd, k, offset=cfg.seed_offset),
                             integrator=fs.moment_integrator, channels=MOMENT_CHANNELS)
            _add_launch(acc, img, n, cfg.max_value)
        done, rnd = want, rnd + 1
        if target is None or done >= cfg.ref_passes:
            break
        mean, err = _moment_stats(acc)
        rel = rel_stderr(mean, err)
        if rel <= target:
            break
        # the passes the measured error predicts, 5% over (the estimate itself is noisy), at least one more
        want = min(cfg.ref_passes, max(done + 1, math.ceil(done * (rel / target) ** 2 * 1.05)))
    mean, err = _moment_stats(acc)
    return _reference(mean, err, done * pass_spp, acc["bad"], T)


def _add_launch(acc: dict, img: np.ndarray, n: int, max_value: float) -> None:
    """Fold one launch (:func:`moment_integrator`'s channels of ``n`` samples a pixel) into ``acc``: a
    pixel weighs as its samples that were not NaN (:func:`valid_moments`); a pixel whose mean is still
    not finite (an Inf sample, or Inf times 0) is left out if NaN, else clamped with variance
    ``max_value**2``. Pixels with any non-finite sample are counted."""
    m, q, f = valid_moments(img)
    nv = n * (1.0 - f)                          # the samples that count, per pixel
    nan = np.isnan(m).any(axis=-1, keepdims=True) | np.isnan(q).any(axis=-1, keepdims=True) | (nv <= 0)
    inf = ~nan & ~(np.isfinite(m).all(axis=-1, keepdims=True) & np.isfinite(q).all(axis=-1, keepdims=True))
    acc["bad"] += int(((f > 0) | ~np.isfinite(img[..., :6]).all(axis=-1, keepdims=True)).sum())
    m = np.where(nan, 0.0, np.clip(m, -max_value, max_value))
    var = np.where(nv > 1, np.maximum(np.where(nan | inf, 0.0, q) - m * m, 0.0) * nv / np.maximum(nv - 1, 1e-300), 0.0)
    var = np.where(inf, max_value * max_value, var)
    w = np.where(nan, 0.0, nv)
    acc["A"] += w * m
    acc["B"] += w * var
    acc["N"] += w


def _moment_stats(acc: dict) -> tuple[np.ndarray, np.ndarray]:
    N = acc["N"]
    has = N > 0
    Nn = np.where(has, N, 1.0)
    return np.where(has, acc["A"] / Nn, 0.0), np.where(has, np.sqrt(acc["B"]) / Nn, 0.0)


def _reference_batch_means(fs: FrameScene) -> dict:
    """``batch_means`` (stores made before ``reference`` existed resume with it): ``ref_passes`` passes,
    each of ``ref_time_slices`` times, consecutive blocks of a shifted van der Corput sequence; the error
    is the batch-means estimate from the pass means."""
    cfg = fs.cfg
    W, H = cfg.res
    passes = cfg.ref_passes
    pass_spp = cfg.ref_spp // passes
    k = fs.ref_time_slices
    shift = _rng(fs.seed, fs.frame, cfg, STREAM_REFERENCE).random()
    times = np.minimum((_van_der_corput(passes * k) + shift) % 1.0, np.nextafter(1.0, 0.0)).reshape(passes, k)
    cnt = np.zeros((H, W, 1))
    s1 = np.zeros((H, W, 3))
    s2 = np.zeros((H, W, 3))
    bad = 0
    done = 0
    mean = std = None
    for p in range(passes):
        img = 0.0
        for j in range(k):
            fs.set_time(float(times[p, j]) if fs.has_motion else 0.0)
            img = img + _mi_render(fs, pass_spp // k, stream_seed(fs.seed, fs.frame, STREAM_REFERENCE, p, j,
                                                                  offset=cfg.seed_offset))
        img = img / k
        nan = np.isnan(img).any(axis=-1, keepdims=True)
        b = ~np.isfinite(img).all(axis=-1)
        bad += int(b.sum())
        img = np.where(nan, 0.0, np.clip(img, -cfg.max_value, cfg.max_value))
        ok = (~nan).astype(np.float64)
        cnt += ok
        s1 += img * ok
        s2 += img * img * ok
        done = p + 1
        if cfg.ref_target_rel_stderr is not None and done >= cfg.ref_min_passes and done < passes:
            mean, std = _batch_stats(cnt, s1, s2)
            if rel_stderr(mean, std) <= cfg.ref_target_rel_stderr:
                break
    mean, std = _batch_stats(cnt, s1, s2)
    return _reference(mean, std, done * pass_spp, bad, k * done if fs.has_motion else 1)


def _batch_stats(cnt, s1, s2):
    n = np.maximum(cnt, 1.0)
    mean = s1 / n
    var = np.maximum(s2 - n * mean * mean, 0.0) / np.maximum(cnt - 1.0, 1.0)
    stderr = np.where(cnt > 1, np.sqrt(var / n), 0.0)
    return mean, stderr


def render_oracle(fs: FrameScene, spp: int) -> np.ndarray:
    """Plain ``mi.render`` (float32, HWC) at ``spp``; time-sliced (up to 16 slices) when the scene moves."""
    img, _ = _sanitize_image(render_sliced(fs, spp, STREAM_ORACLE, 0, max_slices=16), fs.cfg.max_value)
    return img.astype(np.float32)


# ------------------------------------------------------------------------------------------------
# the three parts of a frame (one task each in the dataset graph) and their assembly
INPUT_KEYS = ("radiance", "features", "guides_albedo", "guides_normal", "guides_depth", "guides_motion",
              "camera_to_world", "world_to_clip")
LAYER_KEYS = ("layers",)
REFERENCE_KEYS = ("reference", "reference_stderr")


def _contiguous(out: dict, keys) -> dict:
    for k in keys:
        out[k] = np.ascontiguousarray(out[k], dtype=FRAME_ARRAYS[k][1])
    return out


def inputs_part(fs: FrameScene, sample_hook: Callable | None = None) -> dict:
    """Per-sample inputs of a frame: ``radiance`` (float32, HWS3), ``features`` (float32, HWS17),
    guides (float32, HWC: per-pixel sample means of albedo, normal, depth, motion), ``camera_to_world``
    and ``world_to_clip`` (float64, 4x4), plus ``nonfinite_inputs``, ``has_motion``, ``has_defocus``,
    the scene's ``scene_seed``, ``num_frames``, ``case`` and ``kind`` (what :func:`assemble` records of it) and
    ``seconds``."""
    t0 = _time.perf_counter()
    out = input_samples(fs, sample_hook)
    bad = out.pop("nonfinite")
    out.update(camera_to_world=fs.camera_to_world, world_to_clip=fs.world_to_clip)
    _contiguous(out, INPUT_KEYS)
    fs.set_time(0.0)
    out.update(nonfinite_inputs=int(bad), has_motion=bool(fs.has_motion), has_defocus=bool(fs.has_defocus),
               scene_seed=int(fs.seed), num_frames=int(fs.num_frames), case=str(fs.case), kind=str(fs.kind),
               seconds=_time.perf_counter() - t0)
    return out


def layers_part(fs: FrameScene) -> dict:
    """Sample layers of a frame: ``layers`` (float32, LHW3), ``nonfinite_layers``, ``seconds``."""
    t0 = _time.perf_counter()
    layers, bad = render_layers(fs)
    fs.set_time(0.0)
    return {**_contiguous({"layers": layers}, LAYER_KEYS), "nonfinite_layers": int(bad),
            "seconds": _time.perf_counter() - t0}


def reference_part(fs: FrameScene) -> dict:
    """Reference of a frame: ``reference`` and ``reference_stderr`` (float32, HW3), ``reference_spp``,
    ``reference_rel_stderr``, ``nonfinite_reference``, ``ref_time_slices``, ``seconds``."""
    t0 = _time.perf_counter()
    out = render_reference(fs)
    fs.set_time(0.0)
    return {**_contiguous(out, REFERENCE_KEYS), "seconds": _time.perf_counter() - t0}


def assemble(spec_json: str, frame: int, inputs: dict, layers: dict, reference: dict) -> dict:
    """The ``stores.contract`` frame dict (``FRAME_ARRAYS`` + ``meta``) from the three parts; what it records
    of the scene comes from the inputs part (the loaded scene's), and ``spec_json`` is stored as it is
    (never parsed here: a clip's JSON grows with its length)."""
    out = {k: inputs[k] for k in INPUT_KEYS}
    out.update({k: layers[k] for k in LAYER_KEYS})
    out.update({k: reference[k] for k in REFERENCE_KEYS})
    out["meta"] = {
        "scene_json": spec_json,
        "scene_seed": int(inputs["scene_seed"]),
        "frame": int(frame),
        "num_frames": int(inputs["num_frames"]),
        "has_motion": bool(inputs["has_motion"]),
        "has_defocus": bool(inputs["has_defocus"]),
        "nonfinite_inputs": int(inputs["nonfinite_inputs"]),
        "nonfinite_layers": int(layers["nonfinite_layers"]),
        "nonfinite_reference": int(reference["nonfinite_reference"]),
        "reference_spp": int(reference["reference_spp"]),
        "reference_rel_stderr": float(reference["reference_rel_stderr"]),
        "render_seconds": float(inputs["seconds"] + layers["seconds"] + reference["seconds"]),
        "case": str(inputs["case"]),    # frames/case: the hard cases of the scene (scene_gen.cases), '' for none
        "ref_time_slices": int(reference["ref_time_slices"]),   # distinct shutter times of the reference
        "kind": str(inputs["kind"]),    # frames/kind: the scene family, so that no reader parses the JSON
    }
    if set(out) - {"meta"} != set(FRAME_ARRAYS) or set(out["meta"]) != set(FRAME_META):
        raise RenderError("stores.contract.FRAME_ARRAYS/FRAME_META changed: update pipeline.render.assemble")
    return out


def render_frame(spec: SceneSpec, frame: int, cfg: RenderConfig | None = None, *,
                 on_scene_loaded: Callable | None = None, sample_hook: Callable | None = None) -> dict:
    """Render frame ``frame`` of ``spec``: the ``stores.contract.FRAME_ARRAYS`` dict plus ``meta``
    (:func:`render_loaded` of the frame's :class:`FrameScene`), plus ``oracle``.

    ``on_scene_loaded(scene)`` may modify the freshly loaded ``mi.Scene`` (tests inject NaN emitters
    with it); ``sample_hook`` see :func:`render_inputs`. Raises ``RenderError`` / ``ConfigError``.
    """
    cfg = cfg or RenderConfig()
    if not isinstance(cfg, RenderConfig):
        raise ConfigError(f"cfg must be a RenderConfig, got {type(cfg).__name__}")
    if isinstance(frame, bool) or not isinstance(frame, (int, np.integer)) or not 0 <= frame < spec.num_frames:
        raise RenderError(f"frame {frame!r} out of range: the scene has {spec.num_frames} frame(s)")
    t0 = _time.perf_counter()
    fs = FrameScene(spec, int(frame), cfg, on_scene_loaded)
    load_seconds = _time.perf_counter() - t0
    out = render_loaded(fs, spec.to_json(), sample_hook)
    out["meta"]["render_seconds"] += load_seconds
    return out


def render_loaded(fs: FrameScene, spec_json: str, sample_hook: Callable | None = None) -> dict:
    """The frame of a loaded :class:`FrameScene`: :func:`assemble` of :func:`inputs_part`,
    :func:`layers_part` and :func:`reference_part` on it (the dataset graph's whole-frame task; split,
    its three tasks do it on up to three), plus ``oracle`` when ``cfg.oracle_spp``. ``spec_json`` is the
    scene's JSON, stored as it is."""
    parts = inputs_part(fs, sample_hook), layers_part(fs), reference_part(fs)
    out = assemble(spec_json, fs.frame, *parts)
    if fs.cfg.oracle_spp > 0:
        out["oracle"] = render_oracle(fs, fs.cfg.oracle_spp)
        fs.set_time(0.0)
    return out


def expected_shapes(cfg: RenderConfig) -> dict[str, tuple[tuple[int, ...], str]]:
    """``FRAME_ARRAYS`` with H, W, S, L filled in for ``cfg``."""
    dims = {"H": cfg.height, "W": cfg.width, "S": cfg.spp, "L": cfg.layer_levels}
    return {k: (tuple(dims.get(d, d) for d in shape), dtype) for k, (shape, dtype) in FRAME_ARRAYS.items()}
