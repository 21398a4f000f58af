"""The per-sample renderer: one frame of a scene → the arrays of ``stores.contract``.

One file a part: ``settings`` (:class:`RenderConfig`, seeds, shutter times), ``scene`` (:class:`FrameScene`: the
loaded scene and what the renderer asks of it), ``materials`` (specular colour and roughness asked of the
BSDFs), ``inputs`` (the per-sample input kernel), ``launches`` (every ``mi.render`` call), ``layers``,
``reference`` and ``frame`` (the parts and their assembly). This package reads no ``SceneSpec``: a scene
reaches it loaded (``scene_gen.sources.load_frame``: a generated scene or a user's scene file).

``render_frame(spec, frame, cfg) -> dict`` returns every name of ``FRAME_ARRAYS`` (shapes with
H, W = ``cfg.res[1], cfg.res[0]``, S = ``cfg.spp``, L = ``cfg.layer_levels``), ``meta`` (the keys of
``FRAME_META``) and, when ``cfg.oracle_spp > 0``, ``oracle`` (float32, HWC): plain ``mi.render``.

What is rendered (all with the scene's ``path`` integrator: the scene's bounces, no Russian roulette, the
pixel filter ``cfg.filter``: ``box`` or ``gaussian``):

- **Inputs** (``radiance`` float32 HWS3, ``features`` float32 HWS17): one drjit wavefront of
  W·H·S samples (split in row chunks of at most ``cfg.max_wavefront`` lanes). Each sample draws
  its film position inside its pixel (uniformly for the box filter; from the filter for ``gaussian``,
  so that it estimates the same filtered pixel as ``mi.render``), a lens sample and a wavelength sample from an
  ``independent`` sampler, builds the ray with ``sensor.sample_ray_differential`` and traces it once
  with ``pipeline.primary_path`` (Mitsuba's ``path`` integrator step for step: the same per-sample
  radiance as ``integrator.sample``, times the ray weight), which also hands back the primary hit
  for the features. A pixel's mean therefore estimates what ``mi.render``'s pixel estimates. Each
  wavefront is one drjit kernel that writes its samples, after the NaN/Inf rule, straight into one
  buffer, plus one small kernel for the guides, and one read-back. Features
  (``stores.contract.FEATURE_NAMES``): world shading normal, distance along the ray, diffuse
  albedo (``eval_diffuse_reflectance``, clipped to [0, 1]), specular colour and roughness asked of the
  hit shape's BSDF (``pipeline.render.materials``, a table keyed by shape), motion, CoC,
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
scene time is ``tau = frame + shutter * t`` (frames). Mitsuba has no moving geometry inside one
render, so a scene whose objects move is rendered in time *slices*: the vertex positions of
each moving object are set for the slice's time (``mi.traverse`` + ``update``) and that slice's share
of the samples is rendered. Inputs use ``g = gcd(cfg.time_slices, spp)`` slices with jittered
stratified times ``t_k = (k + u_k) / g`` (samples ``s`` of every pixel in slice ``k = s // (S/g)``,
so samples are ordered by time); each layer likewise with its own jitter (1 spp: one uniform time), with
fewer slices where :func:`reference_time_count` at the layer's samples needs fewer (``moments``);
the reference as above (``batch_means``: ``cfg.ref_time_slices`` times per pass, consecutive blocks of
a randomly shifted van der Corput sequence). The ``time`` feature is the slice time ``t_k``, i.e.
the time the geometry was actually at. A scene without moving objects renders in one pass at
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

Seeds: every sampler seed is ``stream_seed(scene seed, frame, stream, *index, cfg.seed_offset)``
from ``np.random.SeedSequence``: inputs, each layer, each reference pass, time jitter and the oracle
are distinct streams, so no two renders share a seed and the same (spec, frame, cfg) gives identical
bytes (up to ``meta['render_seconds']``).
"""
from pipeline.render.settings import (FILTERS, REFERENCE_METHODS, STREAM_INPUTS, STREAM_LAYER, STREAM_ORACLE,
                                      STREAM_REFERENCE, STREAM_TIME, RenderConfig, reference_time_count,
                                      reference_times, slice_times, stream_seed)
from pipeline.render.scene import FrameScene
from pipeline.render.inputs import (GUIDE_GROUPS, MISS_DISTANCE, MOTION_LIMIT, input_samples, render_inputs,
                                    sample_geometry, sanitize_samples)
from pipeline.render.launches import MAX_LAUNCH_SAMPLES, launch_plan, launch_seed, render_sliced
from pipeline.render.layers import render_layers
from pipeline.render.reference import rel_stderr, render_reference
from pipeline.render.frame import (INPUT_KEYS, LAYER_KEYS, REFERENCE_KEYS, assemble, inputs_part, layers_part,
                                   reference_part, render_frame, render_loaded, render_oracle)

__all__ = ["FILTERS", "REFERENCE_METHODS", "STREAM_INPUTS", "STREAM_LAYER", "STREAM_ORACLE", "STREAM_REFERENCE",
           "STREAM_TIME", "RenderConfig", "reference_time_count", "reference_times", "slice_times", "stream_seed",
           "FrameScene", "GUIDE_GROUPS", "MISS_DISTANCE", "MOTION_LIMIT", "input_samples", "render_inputs",
           "sample_geometry", "sanitize_samples", "MAX_LAUNCH_SAMPLES", "launch_plan", "launch_seed",
           "render_sliced", "render_layers", "rel_stderr", "render_reference", "INPUT_KEYS", "LAYER_KEYS",
           "REFERENCE_KEYS", "assemble", "inputs_part", "layers_part", "reference_part", "render_frame",
           "render_loaded", "render_oracle"]
