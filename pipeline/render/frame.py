"""A frame: its three parts (inputs, layers, reference; one task each in the dataset graph, or one task
for all three on one loaded scene) and their assembly into the ``stores.contract`` frame dict."""
from __future__ import annotations

import time as _time
from typing import Callable

import numpy as np

from pipeline.errors import ConfigError, RenderError
from pipeline.render.inputs import input_samples
from pipeline.render.launches import render_sliced, sanitize_image
from pipeline.render.layers import render_layers
from pipeline.render.reference import render_reference
from pipeline.render.scene import FrameScene
from pipeline.render.settings import STREAM_ORACLE, RenderConfig
from stores.contract import FRAME_ARRAYS, FRAME_META

def render_oracle(fs: FrameScene, spp: int) -> np.ndarray:
    """Plain ``mi.render`` (float32, HWC) at ``spp``; time-sliced (up to 16 slices) when the scene moves."""
    img, _ = sanitize_image(render_sliced(fs, spp, STREAM_ORACLE, 0, max_slices=16), fs.cfg.max_value)
    return img.astype(np.float32)




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
    the scene's ``scene_seed``, ``num_frames``, ``case``, ``kind`` and ``nonfinite_expected`` (what
    :func:`assemble` records of it) and ``seconds``."""
    t0 = _time.perf_counter()
    out = input_samples(fs, sample_hook)
    bad = out.pop("nonfinite")
    out.update(camera_to_world=fs.camera_to_world, world_to_clip=fs.world_to_clip)
    _contiguous(out, INPUT_KEYS)
    fs.set_time(0.0)
    out.update(nonfinite_inputs=int(bad), has_motion=bool(fs.has_motion), has_defocus=bool(fs.has_defocus),
               scene_seed=int(fs.seed), num_frames=int(fs.num_frames), case=str(fs.case), kind=str(fs.kind),
               nonfinite_expected=bool(fs.nonfinite_expected),
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
        "nonfinite_expected": bool(inputs["nonfinite_expected"]),   # its hard case makes NaN on purpose
    }
    if set(out) - {"meta"} != set(FRAME_ARRAYS) or set(out["meta"]) != set(FRAME_META):
        raise RenderError("stores.contract.FRAME_ARRAYS/FRAME_META changed: update pipeline.render.assemble")
    return out


def render_frame(spec, frame: int, cfg: RenderConfig | None = None, *,
                 on_scene_loaded: Callable | None = None, sample_hook: Callable | None = None) -> dict:
    """Render frame ``frame`` of ``spec`` (a ``SceneSpec``: generated, or of a scene file, ``scene_gen.sources``):
    the ``stores.contract.FRAME_ARRAYS`` dict plus ``meta``
    (:func:`render_loaded` of the frame's :class:`FrameScene`), plus ``oracle``.

    ``on_scene_loaded(scene)`` may modify the freshly loaded ``mi.Scene`` (tests inject NaN emitters
    with it); ``sample_hook`` see ``pipeline.render.inputs.input_samples``. Raises ``RenderError`` / ``ConfigError``.
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

