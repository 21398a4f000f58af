"""The frame's scene: a loaded Mitsuba scene plus what the renderer asks of it.

:class:`FrameScene` takes a scene description (a generated ``SceneSpec`` or a user's scene file, both as
``scene_gen.load_frame`` turns them into a ``scene_gen.to_mitsuba.LoadedScene``) and from then on asks
only the loaded scene: materials through its BSDFs (:mod:`pipeline.render.materials`), motion through
the loaded scene's motion description (each moving shape's velocity and ``set_time``), cameras and
their matrices through its camera record. Nothing below reads the description again.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from pipeline.errors import RenderError
from pipeline.render.settings import RenderConfig, reference_time_count
from scene_gen import projection as cam_geom

# Slots of FrameScene.consts (Float: world-to-clip rows x, y, w of this and the previous frame, view axis,
# lens-camera origin and forward axis, CoC factor, focus distance); the input kernel gathers them there,
# so one compiled kernel serves every frame (pipeline.render.inputs).
K_CLIP, K_PREV, K_VIEW, K_EYE, K_FWD, K_COC, K_FOCUS, K_SIZE = 0, 12, 24, 27, 30, 33, 34, 35


class FrameScene:
    """A loaded Mitsuba scene of one frame plus what the renderer needs around it.

    ``set_time(t)`` moves the moving objects to ``tau = frame + shutter * t``; the per-shape tables
    (index 0 = no hit) hold specular colour (float64, N×3) and roughness (N), asked of each shape's BSDF
    (:func:`pipeline.render.materials.bsdf_features`), and velocity (N×3, world units a frame), from the
    loaded scene's motion description. ``merge`` (default; generated scenes): identical materials share
    a BSDF and static objects sharing a material are one mesh (``scene_gen.to_mitsuba.shape_groups``):
    the same image distribution as the unmerged scene, faster (``make bench``: 1.1x on indoor seed 0 at
    128x128). Only one FrameScene should be alive per process while rendering: drjit traces a virtual
    call for every instance alive, so a second scene grows every kernel (``pipeline.tasks``).
    """

    def __init__(self, spec, frame: int, cfg: RenderConfig, on_scene_loaded: Callable | None = None, *,
                 merge: bool = True):
        from core.variant import mitsuba
        from scene_gen.sources import load_frame

        self.mi = mi = mitsuba(threads=cfg.threads or None)
        import drjit as dr
        self.dr = dr
        self.frame, self.cfg = int(frame), cfg
        # the one call from a scene description to a loaded scene: nothing below reads the description
        self.loaded = ld = load_frame(spec, frame, cfg.res, rfilter=cfg.filter, merge=merge, on_loaded=on_scene_loaded)
        self.scene, self.cam, self.prev_cam = ld.scene, ld.camera, ld.prev_camera
        self.seed, self.num_frames, self.case, self.kind = ld.seed, ld.num_frames, ld.case, ld.kind
        self.nonfinite_expected = bool(ld.nonfinite_expected)
        self.merged = bool(merge)
        self.sensor = self.scene.sensors()[0]
        self.integrator = self.scene.integrator()
        self.sampler = mi.load_dict({"type": "independent"})
        self.has_motion, self.has_defocus = ld.has_motion, ld.has_defocus
        self.displacement = ld.shutter_displacement()       # pixels a moving vertex travels in the shutter
        self._moments = None                            # pipeline.render.launches.moments_of
        self.camera_to_world = ld.camera_to_world
        self.view_axis = self.camera_to_world[:3, 2]
        self.world_to_clip, self.prev_world_to_clip = ld.world_to_clip, ld.prev_world_to_clip
        self._check_sensor()
        lut_size = self._shape_tables()
        self.consts, self.consts_u = self._input_constants(lut_size)
        self.integrator_depths = self._path_depths()
        self.film_filter = _film_filter(mi, self.sensor.film(), cfg.filter)
        # the pixels an mi.render launch samples: the film and, for a filter wider than a pixel, its border
        b = int(self.sensor.film().rfilter().border_size()) if self.film_filter is not None else 0
        self.launch_pixels = (cfg.width + 2 * b) * (cfg.height + 2 * b)

    def _shape_tables(self) -> int:
        """The per-shape tables (index 0 = no hit) in numpy and on the drjit side, where the input kernel
        looks them up by registry id - ``lut_base``. Returns the size of that lookup table."""
        from pipeline.render.materials import bsdf_features
        mi, dr = self.mi, self.dr
        shapes = self.scene.shapes()
        ids = np.asarray(dr.reinterpret_array(mi.UInt32, self.scene.shapes_dr()), np.int64).ravel()
        if len(ids) != len(shapes):
            raise RenderError("scene.shapes() and scene.shapes_dr() disagree")
        self.shape_registry_ids = ids
        n = len(shapes) + 1
        self.specular, self.roughness, self.velocity = np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3))
        features: dict[int, tuple] = {}                 # a BSDF shared by many shapes is asked once
        for i, s in enumerate(shapes):
            bsdf = s.bsdf()
            key = id(bsdf)
            if key not in features:
                features[key] = bsdf_features(mi, bsdf)
            self.specular[i + 1], self.roughness[i + 1] = features[key]
            self.velocity[i + 1] = self.loaded.velocity(s.id())
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
        fixed slots ``K_*``, so one compiled kernel serves every frame): a Float array (the two
        world-to-clip matrices' rows x, y, w, the view axis, and for defocus the camera's origin and
        forward axis, the CoC factor and the focus distance) and a UInt32 array (shape-table base, size)."""
        cam = self.cam
        o, f = self.camera_to_world[:3, 3], self.camera_to_world[:3, 2]
        k = (cam.aperture_radius * self.cfg.width / (2.0 * cam.focus_distance * cam_geom.tan_half_fov_x(cam))
             if self.has_defocus else 0.0)
        vals = np.concatenate([self.world_to_clip[[0, 1, 3]].ravel(), self.prev_world_to_clip[[0, 1, 3]].ravel(),
                               self.view_axis, o, f, [k, cam.focus_distance if self.has_defocus else 0.0]])
        assert len(vals) == K_SIZE
        return self.mi.Float(vals.astype(np.float32)), self.mi.UInt32(np.array([self.lut_base, lut_size], np.uint32))

    def _path_depths(self) -> tuple[int, int]:
        """(max_depth, rr_depth) of the scene's ``path`` integrator, which the input loop's own path tracer
        (``pipeline.primary_path``) follows; the loaded scene's ``integrator`` settings are their one source."""
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
        """Time slices of a layer render of ``spp`` samples a pixel (``pipeline.render.layers``; the inputs
        keep ``time_slices``): :func:`reference_time_count` of the frame's motion at those samples, at most
        ``time_slices`` (``moments``; ``batch_means``: ``time_slices``), a divisor of ``spp``; 1 without
        motion."""
        if not self.has_motion:
            return 1
        cap = self.cfg.time_slices
        if self.cfg.reference == "moments":
            cap = reference_time_count(self.displacement, spp, cap)
        return math.gcd(cap, spp)


class FilmFilter:
    """The film's pixel filter as the input loop samples it: ``offsets`` draws a film offset from the
    pixel centre with density proportional to the filter (a ``mi.ContinuousDistribution`` per axis of the
    separable filter, tabulated from Mitsuba's own ``eval``), so a pixel's mean of its samples estimates
    the filtered pixel ``mi.render`` estimates; ``gain`` is how many samples of the pixel's own a sample
    of a filtered ``mi.render`` is worth, ``(integral f)^2 / integral f^2`` over the plane (1 for the
    box), which the reference's standard error needs (``pipeline.render.reference``)."""

    def __init__(self, mi, rfilter, name: str):
        self.name = name
        self.radius = float(rfilter.radius())
        x = np.linspace(-self.radius, self.radius, 1025)
        f = np.maximum(np.asarray(rfilter.eval(mi.Float(x.astype(np.float32))), np.float64), 0.0)
        self.dist = mi.ContinuousDistribution([-self.radius, self.radius], f.astype(np.float32))
        dx = x[1] - x[0]
        fx, f2 = f.sum() * dx, (f * f).sum() * dx       # the ends are 0: the trapezoid rule's sums
        self.gain = float((fx * fx / f2) ** 2)


def _film_filter(mi, film, name: str) -> FilmFilter | None:
    """None for the box filter (uniform film positions in the pixel), else the :class:`FilmFilter`."""
    return None if name == "box" else FilmFilter(mi, film.rfilter(), name)
