"""Pure task functions of the dataset graph (``pipeline.graph`` wires them; Dask runs them).

Every function is a pure function of plain data (a SceneSpec as JSON, a frame index, a render
config as a dict): its result depends on nothing else — not the worker, the retry or the clock (except
the ``*_seconds`` timings, which are metadata). Frames are rendered by three tasks, one per
stream, so references can run on other workers (``pipeline.render`` seeds every stream separately,
so splitting changes no byte):

- :func:`make_spec`        → SceneSpec JSON (str)
- :func:`render_inputs`    → per-sample inputs + guides + camera matrices (dict, see below)
- :func:`render_layers`    → sample layers (dict)
- :func:`render_reference` → reference mean + standard error (dict)
- :func:`write_frame`      → gathers the three parts, writes the frame's region of the store
  (``status/complete`` last) and returns a small summary dict.

:func:`render_whole_frame` is the unsplit alternative (one scene load instead of three).

Each rendering task sizes drjit's thread pool to its Dask worker's thread count, so workers do not
oversubscribe the cores (see NOTES.md).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from stores.contract import FEATURE_GROUPS, FRAME_ARRAYS, FRAME_META

# Keys of each part's result (the frame dict of ``stores.contract`` is their union + ``meta``).
INPUT_KEYS = ("radiance", "features", "guides_albedo", "guides_normal", "guides_depth", "guides_motion",
              "camera_to_world", "world_to_clip")
LAYER_KEYS = ("layers",)
REFERENCE_KEYS = ("reference", "reference_stderr")


def worker_threads() -> int | None:
    """Threads of the Dask worker running this task (None outside a worker)."""
    try:
        from distributed import get_worker
        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None


def _render_cfg(render: dict):
    from pipeline.render import RenderConfig
    cfg = RenderConfig.from_dict(dict(render))
    n = worker_threads()
    if n:
        cfg = dataclasses.replace(cfg, threads=n)
    return cfg


def _frame_scene(spec_json: str, frame: int, render: dict):
    from pipeline.render import FrameScene
    from scene_gen.spec import SceneSpec
    spec = SceneSpec.from_json(spec_json)
    return FrameScene(spec, int(frame), _render_cfg(render))


def make_spec(seed: int, kind: str, num_frames: int, res: tuple[int, int], scene_gen: dict) -> str:
    """The SceneSpec JSON of one scene (``scene_gen.sampling.sample_scene``; ``res`` = (W, H))."""
    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    spec = sample_scene(int(seed), kind, num_frames=int(num_frames), res=int(max(res)),
                        config=SceneGenConfig.from_dict(dict(scene_gen)))
    return spec.to_json()


def render_inputs(spec_json: str, frame: int, render: dict) -> dict:
    """Per-sample inputs of one frame: ``radiance`` (float32, HWS3), ``features`` (float32, HWS17),
    guides (float32, HWC: per-pixel sample means of albedo, normal, depth, motion), ``camera_to_world``
    and ``world_to_clip`` (float64, 4x4), plus ``nonfinite_inputs``, ``has_motion``, ``has_defocus``
    and ``seconds``."""
    from pipeline import render as R
    t0 = time.perf_counter()
    fs = _frame_scene(spec_json, frame, render)
    radiance, features, bad = R.render_inputs(fs)
    out = {
        "radiance": radiance, "features": features,
        "guides_albedo": features[..., FEATURE_GROUPS["albedo"]].mean(axis=2),
        "guides_normal": features[..., FEATURE_GROUPS["normal"]].mean(axis=2),
        "guides_depth": features[..., FEATURE_GROUPS["depth"]].mean(axis=2),
        "guides_motion": features[..., FEATURE_GROUPS["motion"]].mean(axis=2),
        "camera_to_world": fs.camera_to_world, "world_to_clip": fs.world_to_clip,
    }
    for k in INPUT_KEYS:
        out[k] = np.ascontiguousarray(out[k], dtype=FRAME_ARRAYS[k][1])
    out.update(nonfinite_inputs=int(bad), has_motion=bool(fs.has_motion), has_defocus=bool(fs.has_defocus),
               seconds=time.perf_counter() - t0)
    return out


def render_layers(spec_json: str, frame: int, render: dict) -> dict:
    """Sample layers of one frame: ``layers`` (float32, LHW3), ``nonfinite_layers``, ``seconds``."""
    from pipeline import render as R
    t0 = time.perf_counter()
    fs = _frame_scene(spec_json, frame, render)
    layers, bad = R.render_layers(fs)
    return {"layers": np.ascontiguousarray(layers, np.float32), "nonfinite_layers": int(bad),
            "seconds": time.perf_counter() - t0}


def render_reference(spec_json: str, frame: int, render: dict) -> dict:
    """Reference of one frame: ``reference`` and ``reference_stderr`` (float32, HW3), ``reference_spp``,
    ``reference_rel_stderr``, ``nonfinite_reference``, ``seconds``."""
    from pipeline import render as R
    t0 = time.perf_counter()
    fs = _frame_scene(spec_json, frame, render)
    ref, err, spp, rel, bad = R.render_reference(fs)
    return {"reference": np.ascontiguousarray(ref, np.float32),
            "reference_stderr": np.ascontiguousarray(err, np.float32),
            "reference_spp": int(spp), "reference_rel_stderr": float(rel), "nonfinite_reference": int(bad),
            "seconds": time.perf_counter() - t0}


def render_whole_frame(spec_json: str, frame: int, render: dict) -> dict:
    """The whole frame in one task (``pipeline.render.render_frame``): the ``stores.contract`` dict."""
    from pipeline.render import render_frame
    from scene_gen.spec import SceneSpec
    return render_frame(SceneSpec.from_json(spec_json), int(frame), _render_cfg(render))


def assemble(spec_json: str, frame: int, inputs: dict, layers: dict, reference: dict) -> dict:
    """The ``stores.contract`` frame dict (``FRAME_ARRAYS`` + ``meta``) from the three parts."""
    from scene_gen.spec import SceneSpec
    spec = SceneSpec.from_json(spec_json)
    out = {k: inputs[k] for k in INPUT_KEYS}
    out.update({k: layers[k] for k in LAYER_KEYS})
    out.update({k: reference[k] for k in REFERENCE_KEYS})
    out["meta"] = {
        "scene_json": spec_json,
        "scene_seed": int(spec.seed),
        "frame": int(frame),
        "num_frames": int(spec.num_frames),
        "has_motion": bool(inputs["has_motion"]),
        "has_defocus": bool(inputs["has_defocus"]),
        "nonfinite_inputs": int(inputs["nonfinite_inputs"]),
        "nonfinite_layers": int(layers["nonfinite_layers"]),
        "nonfinite_reference": int(reference["nonfinite_reference"]),
        "reference_spp": int(reference["reference_spp"]),
        "reference_rel_stderr": float(reference["reference_rel_stderr"]),
        "render_seconds": float(inputs["seconds"] + layers["seconds"] + reference["seconds"]),
    }
    assert set(out["meta"]) == set(FRAME_META), "stores.contract.FRAME_META changed: update assemble()"
    return out


def write_frame(store: str, index: int, spec_json: str, frame: int, *parts: dict, clip_id: int | None = None) -> dict:
    """Write frame ``index`` of the store from one whole-frame dict or the three parts (inputs,
    layers, reference); ``status/complete[index]`` is set last. ``clip_id`` (the scene's, from
    ``pipeline.config``; default: the scene seed) goes to ``frames/clip_id`` and decides the split.
    Returns a summary: index, frame, scene seed, render and write seconds, reference spp and
    relative standard error, non-finite counts."""
    from stores.writer import StoreWriter
    if len(parts) == 1:
        arrays = parts[0]
    elif len(parts) == 3:
        arrays = assemble(spec_json, frame, *parts)
    else:
        raise TypeError(f"write_frame takes one whole frame or three parts, got {len(parts)}")
    if clip_id is not None:
        arrays = {**arrays, "meta": {**arrays["meta"], "clip_id": int(clip_id)}}
    t0 = time.perf_counter()
    StoreWriter(store).write_frame(int(index), arrays)
    meta = arrays["meta"]
    return {"index": int(index), "frame": int(frame), "scene_seed": int(meta["scene_seed"]),
            "render_seconds": float(meta["render_seconds"]), "write_seconds": time.perf_counter() - t0,
            "reference_spp": int(meta["reference_spp"]), "reference_rel_stderr": float(meta["reference_rel_stderr"]),
            "nonfinite": int(meta["nonfinite_inputs"] + meta["nonfinite_layers"] + meta["nonfinite_reference"])}


def validate_store(store: str) -> dict:
    """Run the store validator; returns its report as a dict (``ok``, ``problems``, ...)."""
    from stores import validate
    return validate.validate_store(store)
