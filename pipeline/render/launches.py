"""How the renderer calls ``mi.render``: launches within drjit's 2^32 samples (:func:`launch_plan`),
time slices for a moving frame (:func:`render_sliced`), the NaN/Inf rule of an image, and the integrator
wrapper whose extra channels give every pixel's second moment in the same launch (:func:`moment_integrator`).
The sample layers and the reference are both made of these calls."""
from __future__ import annotations

import math

import numpy as np

from pipeline.errors import RenderError
from pipeline.render.scene import FrameScene
from pipeline.render.settings import slice_times, stream_seed, time_rng


def sanitize_image(img: np.ndarray, max_value: float) -> tuple[np.ndarray, int]:
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



def mi_render(fs: FrameScene, spp: int, seed: int, *, integrator=None, channels: int = 3) -> np.ndarray:
    """``mi.render`` of ``spp`` samples (float64 HW x ``channels``), in as many launches as :func:`launch_plan`
    says, weighted by their samples; ``integrator`` in place of the scene's own."""
    plan = launch_plan(fs.launch_pixels, int(spp))
    acc = 0.0
    for i, n in enumerate(plan):
        img = fs.mi.render(fs.scene, integrator=integrator, spp=int(n), seed=launch_seed(seed, i))
        if fs.scene.integrator().should_stop():
            # Mitsuba's SIGINT handler cancelled this render: what it returned may hold fewer samples than
            # asked for. Fail the task (it is retried) rather than store a frame that is not what it says.
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
    times = slice_times(time_rng(fs.seed, fs.frame, cfg, stream, index), slices) if fs.has_motion else np.zeros(1)
    acc = 0.0
    for k, t in enumerate(times):
        fs.set_time(float(t))
        acc = acc + mi_render(fs, spp // slices, stream_seed(fs.seed, fs.frame, stream, index, k,
                                                                offset=cfg.seed_offset),
                               integrator=integrator, channels=channels)
    return acc / slices


def moment_integrator(mi, nested):
    """``nested`` (a ``SamplingIntegrator``) wrapped to add four AOVs: the square of each sample's R, G
    and B, and 1 for a sample with a NaN (whose value is then 0). The film's filter averages them per
    pixel (the box: the plain mean of the pixel's samples; another filter: their weighted mean, whose
    error ``pipeline.render.reference`` counts with the filter's gain), so ``mi.render`` returns each pixel's mean, second moment and share of NaN samples in one
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
                return ["m2.R", "m2.G", "m2.B", "nonfinite"]

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


def moments_of(fs: FrameScene):
    """The scene's integrator wrapped by :func:`moment_integrator` (built once a frame scene; the layers
    and the reference share its kernel)."""
    if getattr(fs, "_moments", None) is None:
        fs._moments = moment_integrator(fs.mi, fs.integrator)
    return fs._moments
