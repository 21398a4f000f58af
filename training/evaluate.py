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
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from stores.fitness import reference_limits

from . import accel
from . import checkpoint as ckpt
from . import metrics
from .data import model_dataset, open_store
from .errors import ConfigError
from .models.common import flush_denormals
from .oidn import oidn_denoise

BASELINES = ("input", "oidn")
KINDS = ("indoor", "outdoor", "defocus", "motion", "fireflies", "plain")   # the scene family, then the hard parts

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


def frame_kinds(row: dict) -> list[str]:
    """The kinds of an evaluated frame (``row`` from ``evaluate``): its scene family (indoor or outdoor)
    and any of defocus, motion, fireflies, else plain."""
    kinds = [k for k, key in (("defocus", "has_defocus"), ("motion", "has_motion"),
                              ("fireflies", "has_fireflies")) if row.get(key)]
    scene = [row["scene_kind"]] if row.get("scene_kind") in ("indoor", "outdoor") else []
    return scene + (kinds or ["plain"])


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().permute(1, 2, 0).cpu().numpy()


BASELINE_INPUTS = ("pixels", "sampled-layers")


def baseline_spec(spp: int, kind: str = "pixels"):
    """The baselines' input. ``pixels``: the mean of the first ``spp`` stored samples with those samples'
    albedo and normal, the input a per-pixel model gets at that spp. ``sampled-layers``: ``spp`` samples
    in every pixel composed from the sample layers, with the store's guides, the input of a sampler's
    uniform baseline at that budget (``temporal``)."""
    from .inputs import InputSpec
    if kind not in BASELINE_INPUTS:
        raise ConfigError(f"baseline input must be one of {BASELINE_INPUTS}, got {kind!r}")
    return InputSpec(kind, frames=1, default_spp=spp)


def _uniform_from_layers(item: dict, spp: int) -> torch.Tensor:
    from . import adaptive
    layers = adaptive.clean_layers(item["layers"]).unsqueeze(0)
    return adaptive.compose(layers, adaptive.uniform_counts(layers[:, 0], spp))[0]


def frame_tags(store, idx: int) -> dict:
    """Kinds of store frame ``idx``, whatever the model reads: the scene family, defocus and motion from
    the frame's metadata, fireflies from all of its stored input samples against its reference."""
    rad = torch.from_numpy(np.ascontiguousarray(store.read_array("inputs/radiance", idx)))
    ref = torch.from_numpy(np.ascontiguousarray(store.read_array("reference/radiance", idx)))
    share = firefly_share(rad, ref)
    try:
        scene_kind = str(json.loads(str(store.meta_column("scene_json")[idx]) or "{}").get("kind", ""))
    except ValueError:                       # a synthetic store's placeholder: no family
        scene_kind = ""
    return {"scene_kind": scene_kind, "has_defocus": bool(store.meta_column("has_defocus")[idx]),
            "has_motion": bool(store.meta_column("has_motion")[idx]),
            "firefly_share": share, "has_fireflies": share >= FIREFLY_SHARE}


def evaluate(method, store, split: str = "test", spp: int | None = None, max_frames: int = 0,
             with_flip: bool = True, keep: tuple[int, ...] = (), device: str = "cpu",
             threads: int | None = None, skip_bad_frames: bool = False, baseline_input: str = "pixels",
             progress: bool = False, compile: bool = False, precision: str = "fp32") -> dict:
    """``method``: a checkpoint path, a loaded model, or a baseline name (``input``/``oidn``).

    The model's input declaration chooses the frames it sees (per-sample frames, per-pixel frames at
    ``spp``, windows of a clip ending on each frame). ``spp`` None: the checkpoint's training spp, the
    model's declared default, or for a baseline the store's full sample count; a count the store does
    not hold is refused, and so are frames ``validate`` would flag (``stores.fitness``: non-finite or
    negative values, a non-finite or negative reference standard error, NaN the renderer replaced;
    ``skip_bad_frames`` leaves them out, with a warning naming them). Models run in their inference form (``for_inference``). ``keep``: positions
    (in the split) of frames whose output images (float32 HW3) are returned under ``"images"`` (not
    written to JSON). Times are wall-clock per frame after one warm-up frame. ``device``: ``auto`` is CUDA where present;
    ``compile``: the model through ``torch.compile`` (the warm-up frame compiles); ``precision``: the
    forward pass's autocast (``training.accel``; ``auto``: bf16 on a GPU that has it, else fp32),
    metrics always in fp32."""
    if threads:
        torch.set_num_threads(int(threads))
    flush_denormals()
    dev = accel.pick_device(device)
    device, precision = str(dev), accel.precision_for(precision, dev)
    st = open_store(store)
    info: dict = {"split": split, "store": str(st.path), "torch_threads": torch.get_num_threads(),
                  "device": device, "precision": precision, "compiled": bool(compile)}
    if isinstance(method, str) and method in BASELINES:
        spp = int(st.layout.spp if spp is None else spp)
        spec = baseline_spec(spp, baseline_input)
        info.update(method=method, params=0, fmas_per_pixel=0.0 if method == "input" else None,
                    input_kind=baseline_input)
        model = None
    else:
        if isinstance(method, (str, Path)):
            ck = ckpt.load(method, map_location=device)
            ckpt.check_store(ck, st.schema_version, method)
            model = ckpt.build_model(ck, device)
            spp = int(ck["train_config"].get("spp") or model.input_spec().default_spp) if spp is None else spp
            info.update(method=ck["model"], checkpoint=str(method), train_steps=ck["step"],
                        train_config=ck["train_config"])
        elif isinstance(method, torch.nn.Module):
            model = method.to(device).eval()
            spp = model.input_spec().default_spp if spp is None else spp
            info.update(method=getattr(model, "name", type(model).__name__))
        else:
            raise ConfigError(f"method must be a checkpoint path, a model or one of {BASELINES}, got {method!r}")
        spec = model.input_spec()
        info.update(params=model.param_count(), fmas_per_pixel=float(model.fmas_per_pixel(spp)),
                    model_config=model.config, input_kind=spec.kind)
        model = model.for_inference()
        if compile:
            model = accel.compile_model(model)
    stepwise = model is not None and getattr(model, "stepwise", False)
    if stepwise:                          # a recurrent model: single frames in clip order, carrying its state
        from .inputs import InputSpec
        spec = InputSpec(spec.kind, frames=1, default_spp=spec.default_spp)
    ds = model_dataset(spec, st, split, spp, None, augment=False, seed=0, full_windows=False,
                       skip_bad_frames=skip_bad_frames, progress=progress)
    kind = spec.input_kind
    n = len(ds) if not max_frames else min(int(max_frames), len(ds))
    info["spp"] = spp
    clip_of = st.meta_column("clip_id")
    in_clip = st.meta_column("frame")

    def run(item, state=None):
        """-> (output HW3, new state, achieved mean spp, counts HW or None)."""
        if model is None:
            rad = item["radiance"] if "radiance" in item else _uniform_from_layers(item, spp)
            if method == "input":
                return _hwc(rad), None, float(spp), None
            return oidn_denoise(_hwc(rad), _hwc(item["albedo"]), _hwc(item["normal"])), None, float(spp), None
        with torch.no_grad(), accel.autocast(dev, precision):
            batch = {k: v.unsqueeze(0).to(device) for k, v in item.items()}
            if stepwise:
                out, state, extra = model.step(batch, state)
                counts = extra["counts"][0, 0]
                achieved, counts = float(counts.float().mean()), counts.cpu().numpy()
            else:
                out, achieved, counts = model(batch), float(spp), None
            if out.is_cuda:
                torch.cuda.synchronize()
            return _hwc(out[0]), state, achieved, counts

    frames, images = [], {}
    state, prev_idx, runs, current = None, None, [], []        # runs: consecutive frames of one clip
    sample_map = None
    for pos in range(n):
        item = ds[pos]
        idx = int(item["index"].reshape(-1)[-1])
        follows = (prev_idx is not None and clip_of[idx] == clip_of[prev_idx]
                   and int(in_clip[idx]) == int(in_clip[prev_idx]) + 1)
        if not follows:                                          # a clip starts (or a gap): no history
            state = None
            if len(current) >= 2:
                runs.append(current)
            current = []
        if pos == 0:
            run(item)                                            # warm-up (allocations, OIDN init)
        t = time.perf_counter()
        out, state, achieved, counts = run(item, state)
        ms = (time.perf_counter() - t) * 1e3
        ref = _hwc(kind.target({k: v.unsqueeze(0) for k, v in item.items()})[0])
        h, w = ref.shape[:2]
        row = {"index": idx, "ms": ms, "ms_per_megapixel": ms / (h * w / 1e6), "spp": achieved,
               **metrics.all_metrics(out, ref, with_flip=with_flip), **frame_tags(st, idx)}
        se = item.get("stderr")
        if se is not None:                        # what the reference's own noise lets a metric resolve
            ceiling, floor = reference_limits(ref, _hwc(se[-1] if se.dim() == 4 else se))
            row.update(ref_psnr_ceiling=ceiling, ref_relmse_floor=floor)
        frames.append(row)
        current.append((out, ref))
        if counts is not None and (sample_map is None or (follows and sample_map["clip"] == int(clip_of[idx]))):
            sample_map = {"index": idx, "clip": int(clip_of[idx]), "counts": counts}   # last frame of the first clip
        if pos in keep:
            images[pos] = out
        prev_idx = idx
    if len(current) >= 2:
        runs.append(current)
    keys = [k for k, v in frames[0].items() if k != "index" and not k.startswith(("has_", "ref_"))
            and not isinstance(v, str)] if frames else []
    info["frames"] = frames
    info["mean"] = {k: float(np.mean([f[k] for f in frames])) for k in keys}
    info["by_kind"] = {}
    for kind_name in KINDS:                                     # frames of each kind (they overlap)
        sel = [f for f in frames if kind_name in frame_kinds(f)]
        if sel:
            info["by_kind"][kind_name] = {"frames": len(sel), **{k: float(np.mean([f[k] for f in sel])) for k in keys}}
    # temporal PSNR over each run of consecutive frames of one clip, averaged over the runs (None: no clips)
    tp = [metrics.tpsnr(np.stack([o for o, _ in r]), np.stack([g for _, g in r])) for r in runs]
    info["mean"]["tpsnr"] = float(np.mean(tp)) if tp else None
    info["clips"] = len(runs)
    ceil = [f["ref_psnr_ceiling"] for f in frames if np.isfinite(f.get("ref_psnr_ceiling", np.nan))]
    if ceil:
        floor = [f["ref_relmse_floor"] for f in frames if "ref_relmse_floor" in f]
        info["reference"] = {"psnr_ceiling_median": float(np.median(ceil)), "psnr_ceiling_lowest": float(np.min(ceil)),
                             "relmse_floor_median": float(np.median(floor)), "relmse_floor_highest": float(np.max(floor))}
    info["ms_per_megapixel"] = info["mean"].get("ms_per_megapixel")
    if sample_map is not None:
        info["sample_map"] = sample_map
    if keep:
        info["images"] = images
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
