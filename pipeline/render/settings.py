"""How a frame is rendered: :class:`RenderConfig`, the seeds of every sampler stream, and the rules that
say how many shutter times a render of a moving frame takes (numpy only; nothing here renders)."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from core.checks import is_int, is_number, known_keys, need, need_int
from pipeline.errors import ConfigError

# Sampler streams (the third entry of every seed's SeedSequence).
STREAM_INPUTS, STREAM_LAYER, STREAM_REFERENCE, STREAM_ORACLE, STREAM_TIME = 1, 2, 3, 4, 5
LUMA = np.array([0.2126, 0.7152, 0.0722])
# ``moments`` (the default): per-sample second moments inside each launch, shutter times by the frame's
# motion (:func:`reference_time_count`). ``batch_means``: ``ref_passes`` passes of ``ref_time_slices``
# times each and the batch-means error (the method of stores made before ``reference`` existed).
REFERENCE_METHODS = ("moments", "batch_means")
# Pixel filters (Mitsuba's ``rfilter`` of the film): ``box`` makes a pixel the plain mean of the samples
# inside it; ``gaussian`` (Mitsuba's default film filter, standard deviation 0.5 pixel, radius 2) weighs
# samples of neighbouring pixels too, as most renders users make do (``pipeline.render.inputs``).
FILTERS = ("box", "gaussian")
# The motion rule's bound: rms banding at a moving edge over the reference's own noise there.
BANDING_OVER_NOISE = 0.5


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
    filter: str = "box"                      # the pixel filter (FILTERS) of every image of the frame

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
        self._check_reference_times()
        need(is_int(self.threads) and 0 <= self.threads <= 1024, "render.threads",
             "an integer in [0, 1024] (0 = default)", self.threads, ConfigError)
        need_int("render.seed_offset", self.seed_offset, 0, None, ConfigError)
        need(is_number(self.max_value, finite=True) and self.max_value > 0, "render.max_value",
             "a finite number > 0", self.max_value, ConfigError)
        need_int("render.oracle_spp", self.oracle_spp, 0, None, ConfigError)
        need_int("render.max_wavefront", self.max_wavefront, 1024, None, ConfigError)
        need(self.filter in FILTERS, "render.filter", f"one of {', '.join(FILTERS)}", self.filter, ConfigError)

    def _check_reference_times(self) -> None:
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

    @property
    def width(self) -> int:
        return self.res[0]

    @property
    def height(self) -> int:
        return self.res[1]

    def to_dict(self) -> dict:
        """Plain data; ``filter`` only when it is not ``box``, so the configs recorded by stores made before it
        existed are unchanged (a resume compares them)."""
        d = dataclasses.asdict(self)
        d["res"] = list(self.res)
        if d["filter"] == "box":
            del d["filter"]
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


def time_rng(seed: int, frame: int, cfg: RenderConfig, *index: int) -> np.random.Generator:
    """The time-jitter stream of a scene ``seed``'s frame (``STREAM_TIME``)."""
    return np.random.default_rng(np.random.SeedSequence(
        [int(seed), int(frame), STREAM_TIME, *map(int, index), int(cfg.seed_offset)]))


def van_der_corput(n: int) -> np.ndarray:
    """The first ``n`` points of the base-2 van der Corput sequence (float64)."""
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


def reference_times(times: int) -> np.ndarray:
    """Shutter fractions of a ``moments`` reference with ``times`` distinct times: the centres of equal
    strata (the midpoint rule of :func:`reference_time_count`'s derivation)."""
    return (np.arange(times) + 0.5) / times
