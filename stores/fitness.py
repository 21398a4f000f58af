"""One check of a frame's fitness, used by every command that reads frames: ``validate``, ``train``,
``evaluate``, ``report``, ``hard-cases`` and ``export`` (numpy only).

A frame is fit to train on, evaluate against or hand to another tool when :func:`frame_problems`
finds nothing:

- it is complete (``status/complete``);
- every stored array is finite: per-sample radiance and features, sample layers, reference and its
  standard error, guides, camera matrices (the renderer replaces its NaN/Inf before storing, so a
  non-finite stored value was written by something else, e.g. zarr-python);
- radiance, layers and reference are >= 0, and so is the reference's standard error;
- features and guides lie in their ranges (albedo, roughness and time in [0, 1], lens positions in the
  unit disk, depth >= 0, normals of unit length or 0 on a miss, per-pixel normals no longer than 1:
  a mean of unit vectors), widened by what the store's rounding
  may add (:func:`rounding_tols`);
- its reference is not all zero while its input radiance is not;
- the renderer replaced no NaN/Inf in it (``frames/nonfinite_*``: the stored values are finite, but
  some samples or pixels are substitutes), unless the frame is of the ``nan`` hard case, whose
  renderer NaNs are its purpose (``frames/case``; such a frame is fit, with a note).

Damage (a missing or corrupt chunk) is raised (``StoreCorruptionError``), not returned: it is exit
code 3 everywhere. :func:`screen` checks many frames (threads, a progress bar on long lists) and
refuses them (:class:`~stores.errors.UnfitFrameError` naming each, exit 2) or, with ``skip``, leaves
them out with a warning naming them: the commands' ``--skip-bad-frames``.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field

import numpy as np

from stores.contract import FEATURE_GROUPS, NUM_FEATURES
from stores.errors import UnfitFrameError

TOL = 2e-3                 # float16 features: rel. precision ~5e-4
RELMSE_EPS = 0.01          # as training.metrics.relmse
FRAME_KEYS = ("radiance", "features", "layers", "reference", "reference_stderr", "guides_albedo",
              "guides_normal", "guides_depth", "guides_motion", "camera_to_world", "world_to_clip")
_RENDERER = (("nonfinite_inputs", "input samples"), ("nonfinite_layers", "sample layers"),
             ("nonfinite_reference", "reference"))


@dataclass
class ValueCheck:
    """What :func:`check_values` found in one frame: ``problems`` (empty when fit) and the figures
    ``validate`` prints: NaN/Inf count and value range of each array, the reference's mean relative
    standard error and the metric limits it sets."""
    problems: list = field(default_factory=list)
    nonfinite: dict = field(default_factory=dict)       # array -> count of NaN/Inf
    ranges: dict = field(default_factory=dict)          # array -> [min, max] of finite values
    ref_rel_stderr: float | None = None
    psnr_ceiling: float | None = None
    relmse_floor: float | None = None


def rounding_tols(layout) -> dict[str, float]:
    """The slack the store's encoding needs past a bound of 1 (feature group or guide -> tolerance):
    ``TOL``, or the group's rounding bound ``2**-(k + 1)`` where that is larger (``compact2`` keeps a
    few mantissa bits of some features: a lens point on the unit circle may be stored at radius 1.03)."""
    from stores import schema
    if layout is None:
        return {}
    bits = schema.ARRAY_BY_PATH["inputs/features"].chain(layout).channel_bits(NUM_FEATURES)
    out = {}
    for g, sl in FEATURE_GROUPS.items():
        ks = [k for k in bits[sl] if k is not None]
        out[g] = max([TOL] + [2.0 ** -(k + 1) for k in ks])
    for key, path in (("guides_albedo", "guides/albedo"), ("guides_normal", "guides/normal")):
        k = schema.ARRAY_BY_PATH[path].chain(layout).keepbits
        out[key] = TOL if k is None else max(TOL, 2.0 ** -(k + 1))
    return out


def _range(name, a, lo=None, hi=None, problems=None, tol=TOL, what: str = "values above") -> None:
    fin = a[np.isfinite(a)]
    if fin.size == 0:
        return
    if lo is not None and fin.min() < lo - tol:
        n = int((fin < lo - tol).sum())
        below = "negative values" if lo == 0 else f"values below {lo:g}"
        problems.append(f"{name} has {n} {below} (min {fin.min():.4g})")
    if hi is not None and fin.max() > hi + tol:
        problems.append(f"{name} has {int((fin > hi + tol).sum())} {what} {hi:g} (max {fin.max():.4g})")


def check_values(fr: dict, layout=None) -> ValueCheck:
    """The value checks of one frame in the contract layout (``Store.read_frame``: channel-last,
    float32; any subset of :data:`FRAME_KEYS`). ``layout`` (the store's) widens the range checks by what
    its encoding's rounding may add."""
    out = ValueCheck()
    p = out.problems
    tol = rounding_tols(layout)
    for key, a in fr.items():
        if key == "meta":
            continue
        a = np.asarray(a)
        fin = np.isfinite(a)
        bad = int(a.size - fin.sum())
        out.nonfinite[key] = bad
        if bad:
            p.append(f"{key}: {bad} NaN/Inf values")
        if bad < a.size:
            v = a[fin] if bad else a
            out.ranges[key] = [float(v.min()), float(v.max())]
    for key in ("radiance", "layers", "reference", "reference_stderr"):
        if key in fr:
            _range(key, fr[key], lo=0.0, problems=p, tol=0.0)
    if "features" in fr:
        f, g = fr["features"], FEATURE_GROUPS
        _range("features.albedo", f[..., g["albedo"]], 0.0, 1.0, p, tol.get("albedo", TOL))
        _range("features.roughness", f[..., g["roughness"]], 0.0, 1.0, p, tol.get("roughness", TOL))
        _range("features.time", f[..., g["time"]], 0.0, 1.0, p, tol.get("time", TOL))
        _range("features.depth", f[..., g["depth"]], 0.0, None, p)
        _range("features.lens radius", np.linalg.norm(f[..., g["lens"]], axis=-1), None, 1.0, p, tol.get("lens", TOL))
        n = np.linalg.norm(f[..., g["normal"]], axis=-1)
        odd = np.isfinite(n) & (n > 1e-3) & (np.abs(n - 1) > max(1e-2, tol.get("normal", 0.0)))
        if odd.any():
            p.append(f"features.normal: {int(odd.sum())} samples neither unit length nor 0")
    if "guides_albedo" in fr:
        _range("guides_albedo", fr["guides_albedo"], 0.0, 1.0, p, tol.get("guides_albedo", TOL))
    if "guides_depth" in fr:
        _range("guides_depth", fr["guides_depth"], 0.0, None, p)
    if "guides_normal" in fr:              # a mean of unit vectors: each component, and its length, at most 1
        slack = max(1e-2, tol.get("guides_normal", 0.0))
        _range("guides_normal", fr["guides_normal"], -1.0, 1.0, p, tol=slack)
        length = np.linalg.norm(np.asarray(fr["guides_normal"], np.float64), axis=-1)
        _range("guides_normal", length, None, 1.0, p, tol=slack, what="pixels longer than")
    if "reference" in fr and "radiance" in fr and not np.any(fr["reference"]) and np.any(fr["radiance"]):
        p.append(f"reference is all zero while the input radiance is not "
                 f"(max {float(np.nanmax(fr['radiance'])):.4g})")
    if "reference" in fr and "reference_stderr" in fr:
        ref, se = fr["reference"].astype(np.float64), fr["reference_stderr"].astype(np.float64)
        if np.isfinite(ref).all() and np.isfinite(se).all() and (se >= 0).all():
            out.ref_rel_stderr = float(np.mean(se / np.maximum(np.abs(ref), 1e-3)))
            out.psnr_ceiling, out.relmse_floor = reference_limits(ref, se)
    return out


def reference_limits(ref: np.ndarray, stderr: np.ndarray) -> tuple[float, float]:
    """What a reference's own noise allows a metric to show: the expected PSNR (dB, on tone-mapped
    values, ``core.images.tonemap``, peak 1) and relMSE (``(d - r)^2 / (r^2 + 0.01)``) of the *true*
    image scored against this reference (``ref``, ``stderr``: float, HWC). Delta method: the
    tone-mapped error of a pixel is ``T'(ref) * stderr``, its slope taken by central differences."""
    from core.images import tonemap
    ref = np.asarray(ref, np.float64)
    se = np.asarray(stderr, np.float64)
    h = np.maximum(se, 1e-6)
    slope = (tonemap(ref + h) - tonemap(np.maximum(ref - h, 0.0))) / (ref + h - np.maximum(ref - h, 0.0))
    mse = float(np.mean((slope * se) ** 2))
    psnr = float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))
    return psnr, float(np.mean(se ** 2 / (ref ** 2 + RELMSE_EPS)))


def renderer_findings(meta: dict) -> tuple[list[str], list[str]]:
    """``(problems, notes)`` from a frame's ``frames/nonfinite_*`` counts (``meta``: ``frames_meta``): NaN/Inf
    the renderer replaced are a problem, or a note for a frame whose hard case makes them on purpose
    (``frames/nonfinite_expected``, which the renderer records from the case's declaration)."""
    found = [f"{int(meta[k])} NaN/Inf values in its {what} (replaced by the renderer, frames/{k})"
             for k, what in _RENDERER if int(meta.get(k, 0) or 0)]
    if bool(meta.get("nonfinite_expected", False)):
        return [], [f + f", as its hard case {str(meta.get('case', ''))!r} intends" for f in found]
    return found, []


def frame_problems(st, i: int, *, data: dict | None = None) -> list[str]:
    """Why frame ``i`` of the store ``st`` (a :class:`stores.reader.Store`; ``stores.reader.frame_problems``
    takes a path too) is unfit (module docstring), ``[]`` when it is fit. Reads every array of the frame
    (``data``: already read, in ``Store.read_frame``'s layout). Damage raises ``StoreCorruptionError``."""
    meta = st.frames_meta(i, scene=False)
    if not meta["complete"]:
        return ["incomplete" + (f" (last error: {meta['error']})" if meta["error"] else "")]
    fr = data if data is not None else st.read_frame(i, FRAME_KEYS)
    return check_values(fr, st.layout).problems + renderer_findings(meta)[0]


def check_frames(st, frames, *, progress: bool = False, threads: int | None = None) -> dict[int, list[str]]:
    """:func:`frame_problems` of every frame in ``frames`` of the store ``st`` (in parallel threads:
    decoding and numpy release the GIL), frame -> problems for the unfit ones only. A progress bar on
    stderr for long lists when ``progress``."""
    frames = sorted({int(i) for i in frames})
    st.metadata_damage()                        # fill the metadata cache once, before the threads share it
    n = threads or min(8, max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1))
    bar = None
    if progress and len(frames) >= 64:
        from tqdm import tqdm
        bar = tqdm(total=len(frames), desc="checking frames", unit="frame", dynamic_ncols=True)
    out: dict[int, list[str]] = {}

    def one(i):
        p = frame_problems(st, i)
        if bar is not None:
            bar.update(1)
        return i, p
    try:
        if n > 1 and len(frames) > 1:
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(n, thread_name_prefix="fitness") as pool:
                results = list(pool.map(one, frames))
        else:
            results = [one(i) for i in frames]
    finally:
        if bar is not None:
            bar.close()
    for i, p in results:
        if p:
            out[i] = p
    return out


def describe(bad: dict[int, list[str]], limit: int = 5) -> str:
    """``frame 3: reference has 1 negative values; frame 9: ...`` for the first ``limit`` frames."""
    listed = "; ".join(f"frame {i}: {', '.join(p)}" for i, p in list(sorted(bad.items()))[:limit])
    return listed + (f" (and {len(bad) - limit} more)" if len(bad) > limit else "")


def screen(store, frames, *, skip: bool, what: str, progress: bool = False) -> list[int]:
    """``frames`` that are fit (:func:`screen_items` of single frames)."""
    return screen_items(store, [int(i) for i in frames], skip=skip, what=what, progress=progress)[0]


def screen_items(store, items, *, skip: bool, what: str, also=(), progress: bool = False) -> tuple[list, dict]:
    """The one screen of every consumer: ``items`` (frames, or tuples of frames such as a training item's
    window) whose frames are all fit, and the unfit frames, frame -> problems, through the store's own
    ``check_frames`` (``stores.protocol.TrainingStore``: :func:`check_frames` on a Zarr store, what the
    format holds on a Noisebase folder). ``also``: frames no item uses that count all the same (a
    store's incomplete frames: an unwritten frame's split is not known). Unfit frames raise
    :class:`UnfitFrameError` naming each (``what`` says whose frames: ``"split 'train' of STORE"``),
    unless ``skip``: then the items using them are left out with one warning naming them. Every item
    left out is an error even with ``skip``."""
    items = list(items)
    frames_of = [tuple(int(i) for i in it) if isinstance(it, (tuple, list)) else (int(it),) for it in items]
    used = {i for fr in frames_of for i in fr}
    bad = store.check_frames(sorted(used | {int(i) for i in also}), progress=progress)
    if not bad:
        return items, bad
    listed = describe(bad)
    inside = len(used & set(bad))
    rest = f"; {len(bad) - inside} more incomplete" if len(bad) > inside else ""
    if not skip:
        raise UnfitFrameError(
            f"{len(bad)} frames of {what} would be flagged by validate ({inside} of the {len(used)} used{rest}): "
            f"{listed}; re-render them (python -m pipeline dataset resumes and finishes a partial store; validate "
            "--mark-damaged marks damaged ones), or pass --skip-bad-frames to leave them out", frames=bad)
    keep = [it for it, fr in zip(items, frames_of) if not any(i in bad for i in fr)]
    if not keep:
        raise UnfitFrameError(f"every frame of {what} is flagged by validate: {listed}", frames=bad)
    dropped = "" if all(len(fr) == 1 for fr in frames_of) else f" ({len(items) - len(keep)} items)"
    warnings.warn(f"skipping {len(bad)} flagged frames of {what}{dropped}: {listed}", stacklevel=3)
    return keep, bad


__all__ = ["ValueCheck", "check_values", "reference_limits", "rounding_tols", "renderer_findings",
           "frame_problems", "check_frames", "screen", "screen_items", "describe", "FRAME_KEYS"]
