"""Evaluation of a checkpoint (or a baseline) on held-out frames of a store.

``evaluate(checkpoint, store, split="test")`` returns (and ``write_json`` writes) per-frame
metrics (relMSE, SMAPE, PSNR, SSIM, FLIP; see :mod:`training.metrics`) with the inference time of
each frame in milliseconds per megapixel, their means, the parameter count and the analytic FMAs per
pixel. The model's input declaration (``training.inputs``) chooses what it is fed. Baselines:
``"input"`` (the per-pixel mean of N samples) and ``"oidn"`` (Intel Open Image Denoise on that mean,
with the mean albedo and normal of the same N samples); with ``baseline_input="sampled-layers"`` the
N samples of every pixel are composed from the sample layers and the guides are the store's, as a
sampler's uniform baseline sees them. Each frame is tagged with its kinds (defocus
and motion from the store's frame metadata; fireflies from the input samples, see ``firefly_share``)
and ``by_kind`` holds the means over the frames of each kind.

``mean`` also holds ``spp``, the achieved mean samples per pixel (for an adaptive sampler the mean of
its per-pixel counts, within half a sample of the asked budget; otherwise the count fed), and
``tpsnr``, the temporal PSNR over each run of consecutive frames of one clip, averaged over the runs
(null without clips). Recurrent models (``stepwise``, e.g. ``temporal``) are run clip by clip in frame
order with :meth:`step`, carrying their state; a clip's first frame (or a frame after a gap) starts
without history. Their ``sample_map`` is the count image of the last frame of the first clip.

``ci95`` holds, beside ``mean``, the 95% interval of every mean (``{metric: [low, high]}``): a bootstrap
over the frames with the frames of a clip resampled together (:mod:`training.stats`); null where it
cannot be known (one clip, or a non-finite figure).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from stores.fitness import reference_limits

from . import accel
from . import checkpoint as ckpt
from . import metrics, stats
from .data import model_dataset, open_store
from .errors import ConfigError
from .models.common import flush_denormals
from .oidn import oidn_denoise

BASELINES = ("input", "oidn")

# A sample 16x brighter than its reference pixel (plus 0.05, for black pixels) alone doubles an 8-spp
# mean; a frame "has fireflies" when at least 0.2% of its pixels hold one (test frames of
# configs/train-cpu.yaml: 0 to 1.05%).
FIREFLY_RATIO = 16.0
FIREFLY_SHARE = 0.002


def firefly_share(radiance: torch.Tensor, reference: torch.Tensor) -> float:
    """Share of pixels with a firefly sample: radiance (S 3 H W) linear, reference (3 H W)."""
    lum = torch.tensor([0.2126, 0.7152, 0.0722]).view(3, 1, 1)
    s = (torch.nan_to_num(radiance.float(), nan=0.0, posinf=0.0).clamp(min=0) * lum).sum(dim=-3)   # S H W
    r = (reference.float().clamp(min=0) * lum).sum(dim=0)
    return float((s.amax(dim=0) > FIREFLY_RATIO * (r + 0.05)).float().mean())


HARD_PARTS = ("defocus", "motion", "fireflies", "plain")


def scene_families(store) -> tuple[str, ...]:
    """The scene families the store's frames were made of: the ``kind`` of each scene group of the config
    it records (``scenes: [{kind: indoor, ...}]``), in that order; none for a store made otherwise (a
    synthetic or Noisebase one). Training knows the store, not the scene generator."""
    cfg = store.config if isinstance(store.config, dict) else {}
    kinds = [g.get("kind") for g in cfg.get("scenes", []) if isinstance(g, dict)]
    return tuple(dict.fromkeys(k for k in kinds if isinstance(k, str) and k))


def frame_kinds(row: dict) -> list[str]:
    """The kinds of an evaluated frame (``row`` from ``evaluate``): its scene family (``scene_kind``:
    :func:`frame_tags`) and any of defocus, motion, fireflies, else plain."""
    kinds = [k for k, key in (("defocus", "has_defocus"), ("motion", "has_motion"),
                              ("fireflies", "has_fireflies")) if row.get(key)]
    scene = [row["scene_kind"]] if row.get("scene_kind") else []
    return scene + (kinds or ["plain"])


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().permute(1, 2, 0).cpu().numpy()


def baseline_spec(spp: int, kind: str = "pixels"):
    """The baselines' input: items of input kind ``kind`` (one of ``training.inputs.BASELINE_INPUTS``,
    the ``baseline_input`` of the models' kinds) at ``spp``, seen through the kind's ``noisy_image``.
    ``pixels``: the mean of the first ``spp`` stored samples with those samples' albedo and normal, the
    input a per-pixel model gets at that spp. ``sampled-layers``: ``spp`` samples in every pixel
    composed from the sample layers, with the store's guides, the input of a sampler's uniform
    baseline at that budget (``temporal``)."""
    from .inputs import BASELINE_INPUTS, InputSpec
    if kind not in BASELINE_INPUTS:
        raise ConfigError(f"baseline input must be one of {BASELINE_INPUTS}, got {kind!r}")
    return InputSpec(kind, frames=1, default_spp=spp)


def baseline_groups(evaluated: list[dict], default_spp: int) -> list[tuple[int, str, str]]:
    """``(spp, baseline input, label tag)`` of each baseline evaluation the methods ``evaluated`` (their
    ``evaluate`` results) need: one per spp and ``baseline_input`` of their kinds, so each model stands
    beside the baselines at its own sample count, read as it reads (per-pixel means of stored samples,
    or uniform counts composed from the sample layers). Without methods: the store's spp, per-pixel. The
    tag names the spp and the kind's ``baseline_tag`` when there are several."""
    from .inputs import KINDS
    groups = sorted({(int(e["spp"]), KINDS[e["input_kind"]].baseline_input) for e in evaluated}) or \
        [(int(default_spp), "pixels")]
    several_spp = len({n for n, _ in groups}) > 1
    several_bases = len({b for _, b in groups}) > 1
    return [(n, b, (f" @{n}spp" if several_spp else "") + (KINDS[b].baseline_tag if several_bases else ""))
            for n, b in groups]


def frame_columns(store) -> dict:
    """The per-frame columns :func:`frame_tags` needs, read once for a whole evaluation: the scene family
    (``frames/kind``, :func:`stores.protocol.scene_kinds`; '' outside the families the store's config
    names), defocus and motion."""
    from stores.protocol import scene_kinds
    families = set(scene_families(store))
    return {"scene_kind": [k if k in families else "" for k in scene_kinds(store)],
            "has_defocus": store.meta_column("has_defocus"), "has_motion": store.meta_column("has_motion")}


def frame_tags(store, idx: int, columns: dict | None = None) -> dict:
    """Kinds of store frame ``idx``, whatever the model reads: the scene family, defocus and motion from
    the frame's metadata (``columns``: :func:`frame_columns` of the store, read once), fireflies from all
    of its stored input samples against its reference."""
    cols = frame_columns(store) if columns is None else columns
    rad = torch.from_numpy(np.ascontiguousarray(store.read_array("inputs/radiance", idx)))
    ref = torch.from_numpy(np.ascontiguousarray(store.read_array("reference/radiance", idx)))
    share = firefly_share(rad, ref)
    return {"scene_kind": str(cols["scene_kind"][idx]), "has_defocus": bool(cols["has_defocus"][idx]),
            "has_motion": bool(cols["has_motion"][idx]), "firefly_share": share, "has_fireflies": share >= FIREFLY_SHARE}


# --------------------------------------------------------------------------------------------
# The method: a model or a baseline, and how it is run on one item


@dataclass
class Method:
    """What ``evaluate`` runs: ``model`` (None for a baseline) in its inference form, its input ``spec``,
    the ``spp`` it is fed, and what the result records of it (``info``)."""

    name: str
    model: torch.nn.Module | None
    spec: object
    spp: int
    info: dict

    @property
    def stepwise(self) -> bool:
        return self.model is not None and bool(getattr(self.model, "stepwise", False))


def load_method(method, st, spp: int | None, device: str, compile: bool, baseline_input: str) -> Method:
    """``method``: a checkpoint path, a loaded model, or a baseline name (:data:`BASELINES`)."""
    if isinstance(method, str) and method in BASELINES:
        spp = int(st.layout.spp if spp is None else spp)
        return Method(method, None, baseline_spec(spp, baseline_input), spp,
                      dict(method=method, params=0, fmas_per_pixel=0.0 if method == "input" else None,
                           input_kind=baseline_input))
    if isinstance(method, (str, Path)):
        ck = ckpt.load(method, map_location=device)
        model = ckpt.build_model(ck, device)
        spp = int(ck["train_config"].get("spp") or model.input_spec().default_spp) if spp is None else spp
        info = dict(method=ck["model"], checkpoint=str(method), train_steps=ck["step"], train_config=ck["train_config"])
    elif isinstance(method, torch.nn.Module):
        model = method.to(device).eval()
        spp = model.input_spec().default_spp if spp is None else spp
        info = dict(method=getattr(model, "name", type(model).__name__))
    else:
        raise ConfigError(f"method must be a checkpoint path, a model or one of {BASELINES}, got {method!r}")
    spec = model.input_spec()
    info.update(params=model.param_count(), fmas_per_pixel=float(model.fmas_per_pixel(spp)),
                model_config=model.config, input_kind=spec.kind)
    fast = model.for_inference()
    return Method(info["method"], accel.compile_model(fast) if compile else fast, spec, int(spp), info)


def _sync(dev: torch.device) -> None:
    """Wait for ``dev``'s queued work (a CUDA device's own stream; nothing to wait for on the CPU)."""
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def runner(m: Method, dev: torch.device, precision: str):
    """``run(item, state) -> (output HW3, new state, achieved mean spp, counts HW or None, ms)`` for one
    item (no batch axis). A baseline sees the kind's ``noisy_image``; a recurrent model steps once,
    carrying ``state``; ``counts`` is an adaptive sampler's count image (``extra["counts"]`` of its step).
    ``ms``: the model's step alone, from its inputs on ``dev`` to its output there (``dev`` synchronized
    on both sides): the upload before and the read-back after are not in it (a baseline: the whole call,
    which has no transfer)."""
    kind = m.spec.input_kind

    def run(item, state=None):
        if m.model is None:
            t = time.perf_counter()
            im = {k: _hwc(v) for k, v in kind.noisy_image(item, m.spp).items()}
            out = im["radiance"] if m.name == "input" else oidn_denoise(im["radiance"], im.get("albedo"), im.get("normal"))
            return out, None, float(m.spp), None, (time.perf_counter() - t) * 1e3
        batch = {k: v.unsqueeze(0).to(dev) for k, v in item.items()}
        _sync(dev)
        t = time.perf_counter()
        with torch.no_grad(), accel.autocast(dev, precision):
            out, state, extra = kind.stream(m.model, batch, state)
        _sync(dev)
        ms = (time.perf_counter() - t) * 1e3
        counts = extra.get("counts")
        if counts is None:
            return _hwc(out[0]), state, float(m.spp), None, ms
        counts = counts[0, 0]
        return _hwc(out[0]), state, float(counts.float().mean()), counts.cpu().numpy(), ms
    return run


# --------------------------------------------------------------------------------------------
# Frames, in clip order


def evaluate_frames(m: Method, ds, st, n: int, run, with_flip: bool, keep) -> dict:
    """Run ``m`` on the first ``n`` items of ``ds`` in order: per-frame rows (metrics, times, tags,
    the reference's limits), runs of consecutive frames of one clip (``(output, reference)`` pairs, for
    tPSNR), the kept images and a sampler's count image (the last frame of the first clip). A clip's
    first frame, or a frame after a gap, starts a recurrent model without history."""
    kind = m.spec.input_kind
    clip_of, in_clip, columns = st.meta_column("clip_id"), st.meta_column("frame"), frame_columns(st)
    rows, runs, images, sample_map = [], [], {}, None
    state, prev, current, warmed, warmups = None, None, [], set(), 0
    warmup_calls = int(getattr(m.model, "warmup_calls", 1))    # 2 where CUDA graphs record on the 2nd call
    for pos in range(n):
        item = ds[pos]
        idx = int(item["index"].reshape(-1)[-1])
        follows = prev is not None and clip_of[idx] == clip_of[prev] and int(in_clip[idx]) == int(in_clip[prev]) + 1
        if not follows:                                          # a clip starts (or a gap): no history
            state = None
            runs.append(current)
            current = []
        sig = call_signature(item, state)
        if sig not in warmed:              # warm-up: allocations, OIDN's start, a compiled model's (re)compile
            warmed.add(sig)
            for _ in range(warmup_calls):
                run(item, state)
                warmups += 1
        out, state, achieved, counts, ms = run(item, state)
        ref = _hwc(kind.target({k: v.unsqueeze(0) for k, v in item.items()})[0])
        rows.append(frame_row(st, idx, int(clip_of[idx]), out, ref, item.get("stderr"), ms, achieved, with_flip,
                              columns))
        current.append((out, ref, idx))
        if counts is not None and (sample_map is None or (follows and sample_map["clip"] == int(clip_of[idx]))):
            sample_map = {"index": idx, "clip": int(clip_of[idx]), "counts": counts}
        if pos in keep:
            images[pos] = out
        prev = idx
    runs = [r for r in runs + [current] if len(r) >= 2]
    return {"frames": rows, "runs": runs, "images": images, "sample_map": sample_map,
            "timing": {"frames_timed": len(rows), "untimed_warmups": warmups, "call_signatures": len(warmed),
                       "measures": TIMING_MEASURES}}


TIMING_MEASURES = ("a frame's ms: the model's step from its inputs on the device to its output there, the device "
                   "synchronized on both sides; the upload before and the read-back after are not in it (baselines: "
                   "the whole call)")


def call_signature(item: dict, state) -> tuple:
    """What decides whether a compiled model runs code it has compiled already: the shapes and dtypes of
    the item's tensors and of a recurrent model's state (None on a clip's first step)."""
    def shapes(x):
        if isinstance(x, torch.Tensor):
            return (tuple(x.shape), str(x.dtype))
        if isinstance(x, dict):
            return tuple((k, shapes(v)) for k, v in sorted(x.items()))
        if isinstance(x, (list, tuple)):
            return tuple(shapes(v) for v in x)
        return None if x is None else type(x).__name__
    return shapes(item), shapes(state)


def frame_row(st, idx: int, clip: int, out, ref, stderr, ms: float, achieved: float, with_flip: bool,
              columns: dict | None = None) -> dict:
    h, w = ref.shape[:2]
    row = {"index": idx, "clip": clip, "ms": ms, "ms_per_megapixel": ms / (h * w / 1e6), "spp": achieved,
           **metrics.all_metrics(out, ref, with_flip=with_flip), **frame_tags(st, idx, columns)}
    if stderr is not None:                        # what the reference's own noise lets a metric resolve
        ceiling, floor = reference_limits(ref, _hwc(stderr[-1] if stderr.dim() == 4 else stderr))
        row.update(ref_psnr_ceiling=ceiling, ref_relmse_floor=floor)
    return row


# --------------------------------------------------------------------------------------------
# Summaries


def metric_keys(frames: list[dict]) -> list[str]:
    """The numeric per-frame figures that are averaged (not the frame's index, clip, tags or limits)."""
    return [k for k, v in frames[0].items() if k not in ("index", "clip") and not k.startswith(("has_", "ref_"))
            and not isinstance(v, str)] if frames else []


def summarize(frames: list[dict], runs: list) -> dict:
    """``mean`` and ``ci95`` of every figure (:mod:`training.stats`: a bootstrap over clips), the means
    by kind of frame, tPSNR over the runs of one clip, and the reference's limits."""
    keys = metric_keys(frames)
    clips = [f["clip"] for f in frames]
    out = {"mean": {k: float(np.mean([f[k] for f in frames])) for k in keys},
           "ci95": {k: stats.mean_ci([f[k] for f in frames], clips) for k in keys},
           "by_kind": by_kind(frames, keys)}
    tp = [metrics.tpsnr(np.stack([o for o, _, _ in r]), np.stack([g for _, g, _ in r])) for r in runs]
    out["mean"]["tpsnr"] = float(np.mean(tp)) if tp else None
    out["ci95"]["tpsnr"] = stats.mean_ci(tp) if tp else None        # one value a clip: clips resampled whole
    # each run's tPSNR by its first frame, so a report can pair two methods run by run
    out["tpsnr_runs"] = {str(r[0][2]): float(v) for r, v in zip(runs, tp)}
    out["clips"] = len(runs)
    ref = reference_summary(frames)
    if ref:
        out["reference"] = ref
    out["ms_per_megapixel"] = out["mean"].get("ms_per_megapixel")
    return out


def by_kind(frames: list[dict], keys: list[str]) -> dict:
    """Means over the frames of each kind (:func:`frame_kinds`; a frame may have several): the scene
    families first (in the order the frames show them), then the hard parts; each with ``ci95``, the
    95% interval of every mean (a bootstrap over clips), and ``same_as``, the earlier kind whose frames
    are exactly these (defocus and motion on a store where every indoor scene has both), or None."""
    tags = [frame_kinds(f) for f in frames]
    order = list(dict.fromkeys(f["scene_kind"] for f in frames if f.get("scene_kind"))) + list(HARD_PARTS)
    out, seen = {}, {}
    for kind in order:
        sel = [f for f, t in zip(frames, tags) if kind in t]
        if sel:
            ids = tuple(f["index"] for f in sel)
            clips = [f.get("clip", f["index"]) for f in sel]
            out[kind] = {"frames": len(sel), **{k: float(np.mean([f[k] for f in sel])) for k in keys},
                         "ci95": {k: stats.mean_ci([f[k] for f in sel], clips) for k in keys},
                         "same_as": seen.get(ids)}
            seen.setdefault(ids, kind)
    return out


def reference_summary(frames: list[dict]) -> dict:
    ceil = [f["ref_psnr_ceiling"] for f in frames if np.isfinite(f.get("ref_psnr_ceiling", np.nan))]
    if not ceil:
        return {}
    floor = [f["ref_relmse_floor"] for f in frames if "ref_relmse_floor" in f]
    return {"psnr_ceiling_median": float(np.median(ceil)), "psnr_ceiling_lowest": float(np.min(ceil)),
            "relmse_floor_median": float(np.median(floor)), "relmse_floor_highest": float(np.max(floor))}


# --------------------------------------------------------------------------------------------
# evaluate


def evaluate(method, store, split: str = "test", spp: int | None = None, max_frames: int = 0,
             with_flip: bool = True, keep: tuple[int, ...] = (), device: str = "cpu",
             threads: int | None = None, skip_bad_frames: bool = False, baseline_input: str = "pixels",
             progress: bool = False, compile: bool = False, precision: str = "fp32") -> dict:
    """``method``: a checkpoint path, a loaded model, or a baseline name (``input``/``oidn``).

    The model's input declaration chooses the frames it sees (per-sample frames, per-pixel frames at
    ``spp``, windows of a clip ending on each frame; a recurrent model single frames in clip order).
    ``spp`` None: the checkpoint's training spp, the model's declared default, or for a baseline the
    store's full sample count; a count the store does not hold is refused, and so are frames
    ``validate`` would flag (``stores.fitness``: non-finite or negative values, a non-finite or
    negative reference standard error, NaN the renderer replaced; ``skip_bad_frames`` leaves them out,
    with a warning naming them). Models run in their inference form (``for_inference``). ``keep``:
    positions (in the split) of frames whose output images (float32 HW3) are returned under
    ``"images"`` (not written to JSON). Times are wall-clock per frame after one warm-up frame.
    ``device``: ``auto`` is CUDA where present; ``compile``: the model through ``torch.compile`` (the
    warm-up frame compiles); ``precision``: the forward pass's autocast (``training.accel``; ``auto``:
    bf16 on a GPU that has it, else fp32), metrics always in fp32."""
    if threads:
        torch.set_num_threads(int(threads))
    flush_denormals()
    dev = accel.pick_device(device)
    precision = accel.precision_for(precision, dev)
    st = open_store(store)
    m = load_method(method, st, spp, str(dev), compile, baseline_input)
    spec = replace(m.spec, frames=1) if m.stepwise else m.spec     # single frames, the model's features kept
    ds = model_dataset(spec, st, split, m.spp, None, augment=False, seed=0, full_windows=False,
                       skip_bad_frames=skip_bad_frames, progress=progress)
    n = len(ds) if not max_frames else min(int(max_frames), len(ds))
    done = evaluate_frames(m, ds, st, n, runner(m, dev, precision), with_flip, keep)
    info = {"split": split, "store": str(st.path), "torch_threads": torch.get_num_threads(), "device": str(dev),
            "precision": precision, "compiled": bool(compile), **m.info, "spp": m.spp, "frames": done["frames"],
            "left_out": {str(i): list(p) for i, p in sorted(ds.left_out.items())},
            **summarize(done["frames"], done["runs"])}
    info["timing"] = {**done["timing"], "what": "ms per frame of calls whose input shapes (and a recurrent "
                      "model's state) ran before, untimed (once; twice where CUDA graphs record on the second "
                      "call): no compilation, graph recording or first-call cost is counted"}
    if done["sample_map"] is not None:
        info["sample_map"] = done["sample_map"]
    if keep:
        info["images"] = done["images"]
    return info


def write_json(result: dict, path) -> None:
    """``result`` as strict JSON (:func:`training.jsonio.dumps`: a non-finite number, e.g. the PSNR of an
    exact output or the ceiling of a noiseless reference, is ``null``), written atomically."""
    from .jsonio import write
    path = Path(path)
    clean = {k: v for k, v in result.items() if k not in ("images", "sample_map")}
    if "sample_map" in result:                   # the counts image stays out of the JSON; its frame and mean do not
        sm = result["sample_map"]
        clean["sample_map"] = {"index": sm["index"], "mean_spp": float(np.mean(sm["counts"])),
                               "max_spp": int(np.max(sm["counts"]))}
    write(path, clean)
