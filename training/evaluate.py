"""Evaluation of a checkpoint (or a baseline) on held-out frames of a store.

``evaluate(checkpoint, store, split="test", spp=8)`` returns (and ``write_json`` writes) per-frame
metrics (relMSE, SMAPE, PSNR, SSIM, FLIP; see :mod:`training.metrics`) with the inference time of
each frame in milliseconds per megapixel, their means, the parameter count and the analytic FMAs per
pixel. Baselines: ``"input"`` (the per-pixel mean of the samples) and ``"oidn"`` (Intel Open Image
Denoise on that mean, with the albedo and normal guides). Each frame is tagged with its kinds (defocus
and motion from the store's frame metadata; fireflies from the input samples, see ``firefly_share``)
and ``by_kind`` holds the means over the frames of each kind.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from . import checkpoint as ckpt
from . import metrics
from .data import open_store, sample_dataset
from .errors import ConfigError
from .models.common import flush_denormals
from .oidn import oidn_denoise

BASELINES = ("input", "oidn")
KINDS = ("defocus", "motion", "fireflies", "plain")

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
    """The kinds of an evaluated frame (``row`` from ``evaluate``): any of defocus, motion, fireflies,
    else plain."""
    kinds = [k for k, key in (("defocus", "has_defocus"), ("motion", "has_motion"),
                              ("fireflies", "has_fireflies")) if row.get(key)]
    return kinds or ["plain"]


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().permute(1, 2, 0).cpu().numpy()


def _frames(store, split, spp, max_frames):
    st = open_store(store)
    spp = min(int(spp), st.layout.spp)
    ds = sample_dataset(st, split, spp, None, augment=False, seed=0)
    n = len(ds) if not max_frames else min(int(max_frames), len(ds))
    return st, ds, n, spp


def evaluate(method, store, split: str = "test", spp: int = 8, max_frames: int = 0, with_flip: bool = True,
             keep: tuple[int, ...] = (), device: str = "cpu", threads: int | None = None) -> dict:
    """``method``: a checkpoint path, a loaded model, or a baseline name (``input``/``oidn``).
    ``keep``: positions (in the split) of frames whose output images (float32 HW3) are returned under
    ``"images"`` (not written to JSON). Times are wall-clock per frame after one warm-up frame."""
    if threads:
        torch.set_num_threads(int(threads))
    flush_denormals()
    st, ds, n, spp = _frames(store, split, spp, max_frames)
    info: dict = {"split": split, "spp": spp, "store": str(st.path), "torch_threads": torch.get_num_threads()}
    if isinstance(method, str) and method in BASELINES:
        info.update(method=method, params=0, fmas_per_pixel=0.0 if method == "input" else None)
        model = None
    else:
        if isinstance(method, (str, Path)):
            ck = ckpt.load(method, map_location=device)
            ckpt.check_store(ck, st.schema_version, method)
            model = ckpt.build_model(ck, device)
            info.update(method=ck["model"], checkpoint=str(method), train_steps=ck["step"],
                        train_config=ck["train_config"])
        elif isinstance(method, torch.nn.Module):
            model = method.to(device).eval()
            info.update(method=getattr(model, "name", type(model).__name__))
        else:
            raise ConfigError(f"method must be a checkpoint path, a model or one of {BASELINES}, got {method!r}")
        info.update(params=model.param_count(), fmas_per_pixel=float(model.fmas_per_pixel(spp)),
                    model_config=model.config)

    def run(item):
        if model is None:
            mean = item["radiance"].mean(dim=0)
            if method == "input":
                return _hwc(mean)
            return oidn_denoise(_hwc(mean), _hwc(item["albedo"]), _hwc(item["normal"]))
        with torch.no_grad():
            batch = {k: v.unsqueeze(0).to(device) for k, v in item.items()}
            out = model(batch)
            if out.is_cuda:
                torch.cuda.synchronize()
            return _hwc(out[0])

    defocus, motion = st.meta_column("has_defocus"), st.meta_column("has_motion")
    frames, images = [], {}
    for pos in range(n):
        item = ds[pos]
        if pos == 0:
            run(item)                                            # warm-up (allocations, OIDN init)
        t = time.perf_counter()
        out = run(item)
        ms = (time.perf_counter() - t) * 1e3
        ref = _hwc(item["reference"])
        h, w = ref.shape[:2]
        idx = int(item["index"])
        share = firefly_share(item["radiance"], item["reference"])
        row = {"index": idx, "ms": ms, "ms_per_megapixel": ms / (h * w / 1e6),
               **metrics.all_metrics(out, ref, with_flip=with_flip),
               "has_defocus": bool(defocus[idx]), "has_motion": bool(motion[idx]),
               "firefly_share": share, "has_fireflies": share >= FIREFLY_SHARE}
        frames.append(row)
        if pos in keep:
            images[pos] = out
    keys = [k for k in frames[0] if k != "index" and not k.startswith("has_")] if frames else []
    info["frames"] = frames
    info["mean"] = {k: float(np.mean([f[k] for f in frames])) for k in keys}
    info["by_kind"] = {}
    for kind in KINDS:                                          # frames of each kind (they overlap)
        sel = [f for f in frames if kind in frame_kinds(f)]
        if sel:
            info["by_kind"][kind] = {"frames": len(sel), **{k: float(np.mean([f[k] for f in sel])) for k in keys}}
    info["ms_per_megapixel"] = info["mean"].get("ms_per_megapixel")
    if keep:
        info["images"] = images
    return info


def write_json(result: dict, path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    clean = {k: v for k, v in result.items() if k != "images"}
    path.write_text(json.dumps(clean, indent=2, default=float))
