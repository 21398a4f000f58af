"""The ``noisebase`` export: a store's clips as Noisebase ``sampleset_v1`` sequences.

``python -m pipeline export STORE --format noisebase --out DIR`` writes one Zarr v2 zip store per clip,
``DIR/scene0000.zip`` ..., in the layout of :mod:`stores.noisebase` (the arrays Noisebase's own
``TrainingSampleLoader_v1`` reads), plus ``DIR/noisebase.yaml`` (the dataset definition its loaders
take: ``src.sequences``, ``files``, ``frames_per_sequence``, ``crop``, ``samples``,
``rendering_height``, ``rendering_width``) and ``DIR/sequences.json`` (which store clip and frames each
file holds, and its split).

What each array holds:

* ``color`` and ``exposure``: the stored per-sample radiance, RGBE-encoded (:func:`stores.noisebase.rgbe_encode`,
  dithered with a generator seeded by the scene seed and frame, so an export is reproducible);
* ``position`` and ``motion``: **exact** world-space geometry of every stored sample. The store keeps
  depth, not the sample's film position, so a position rebuilt from depth and the pixel centre would be
  off by up to half a pixel; instead the exporter re-traces the frame's input samples
  (:func:`pipeline.render.sample_geometry`: the same seeds, film positions, lens and time samples as
  the render, to their first hit, unshaded; a few percent of the input render's time) and checks every
  sample's depth against the stored one (within the store's rounding) before it writes anything. A miss
  is placed :data:`pipeline.render.MISS_DISTANCE` along its ray; ``motion`` is the hit point's position
  one frame earlier minus its position now (0 on a miss);
* ``normal`` and ``diffuse`` (float16): the stored ``normal`` (world) and ``albedo`` features;
* ``reference``: the stored reference;
* ``camera_*``, ``proj_mat``, ``view_proj_mat``: the frame's camera (:func:`stores.noisebase.camera`),
  ``crop_offset`` 0 (a sequence is whole frames).

Sequences are whole clips of one length (Noisebase has one ``frames_per_sequence``): frames of a clip
that ``--frames`` leaves out, stills, and clips of different lengths are refused with a message naming
them. A clip holding a frame that ``--skip-bad-frames`` leaves out is split there, never joined across
it: each run of frames before and after it that is as long as the other sequences (the whole clips', or
without any the length that keeps the most frames, two at least) becomes a sequence of its own, and the
rest of the clip is left out, with one line naming each clip split or left out (:func:`clip_sequences`). Our features without a Noisebase array (specular, roughness, CoC, lens, time) are not exported.
Non-square frames are written as they are; Noisebase's flip/rotate augmentation assumes square crops,
so turn it off (``flip_rotate: false``) for them.
"""
from __future__ import annotations

import json
import os

import numpy as np

from stores import noisebase as nb
from stores.contract import FEATURE_GROUPS, FEATURE_NAMES
from stores.errors import ExportError

RGBE_SALT = 0x4E42     # "NB": the dither stream of the RGBE encoding
DEPTH_SLACK = 2.0 ** -7   # relative: twice the coarsest stored depth rounding (compact2/3 keep 8 bits)


def _runs(frames: list[int]) -> list[list[int]]:
    """The maximal runs of consecutive values of the sorted ``frames``."""
    out: list[list[int]] = []
    for i in frames:
        if out and i == out[-1][-1] + 1:
            out[-1].append(i)
        else:
            out.append([i])
    return out


def _span(run: list[int]) -> str:
    return f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0])


def clip_sequences(store, frames: list[int], left_out=None) -> tuple[list[tuple[int, list[int]]], list[str]]:
    """``(sequences, notes)``: ``(clip id, its frames in clip order)`` of every sequence to write, in store
    order, and what was done to the clips holding a frame of ``left_out`` (the frames ``--skip-bad-frames``
    left out). Clips ``frames`` covers whole are one sequence each. A clip whose frames are all chosen but
    those of ``left_out`` is split there into its runs of consecutive frames (never joined across one), and
    each run as long as the sequences (the whole clips' length, or without whole clips the length that
    keeps the most frames; two frames at least) is a sequence of its own; a note names each clip split or
    left out. Refused (ExportError): clips that ``frames`` covers in part, a frame inside a clip that is
    not complete and not left out, stills, whole clips of different lengths, and no sequence at all."""
    chosen = set(int(i) for i in frames)
    whole, split = _sort_clips(store, chosen, {int(i) for i in (left_out or {})})
    size = _sequence_length(whole, split)
    out, notes = list(whole), []
    for c, runs, cut in split:
        kept = [r for r in runs if len(r) == size]
        out += [(c, r) for r in kept]
        notes.append(_split_note(c, runs, cut, kept, size))
    if not out:
        raise ExportError("no Noisebase sequence is left to write: " + "; ".join(notes[:5])
                          + (f" (and {len(notes) - 5} more)" if len(notes) > 5 else ""))
    return sorted(out, key=lambda t: t[1][0]), notes


def _sort_clips(store, chosen: set, skipped: set) -> tuple[list, list]:
    """``(whole, split)``: the clips ``chosen`` covers whole, as ``(clip id, frames)``, and those to split
    at frames of ``skipped``, as ``(clip id, runs of chosen frames, frames cut)``; ExportError for what
    :func:`clip_sequences` refuses."""
    clip_of = store.meta_column("clip_id")
    position, length = store.meta_column("frame"), store.meta_column("num_frames")
    whole, split, partial, gaps, touched = [], [], [], [], set()
    for c, idx in store.clips(None).items():
        first, n = idx[0] - int(position[idx[0]]), int(length[idx[0]])     # a clip's frames are consecutive
        # the clip's frames left out: those between its complete ones, and those its recorded metadata places in it
        cut = sorted(i for i in skipped if idx[0] < i < idx[-1] or (
            0 <= i < len(clip_of) and int(clip_of[i]) == c and i - int(position[i]) == first))
        have = [i for i in idx if i in chosen]
        if not have and not cut:
            continue
        touched.update(idx)
        span = range(min([idx[0]] + cut), max([idx[-1]] + cut) + 1)
        complete = set(idx)
        absent = [i for i in span if i not in complete and i not in skipped]
        other = [i for i in idx if i not in chosen and i not in skipped]
        if absent:                  # a frame inside the clip is not complete: never join its neighbours across it
            gaps.append(f"clip {c} has no complete frame {', '.join(str(i) for i in absent[:5])} "
                        f"(position {', '.join(str(i - first) for i in absent[:5])} of its {n})")
        elif other:
            partial.append(f"clip {c} (frames {idx[0]}-{idx[-1]}; {len(have)} of {len(idx)} chosen)")
        elif cut:
            split.append((int(c), _runs(have), cut))
        else:
            whole.append((int(c), list(idx)))
    if gaps:
        raise ExportError("a Noisebase sequence is a run of consecutive frames, never joined across a gap: "
                          + "; ".join(gaps[:5]) + ": render the frames again (the same `python -m pipeline "
                          "dataset` command resumes them), leave the clips out (--frames), or pass "
                          "--skip-bad-frames to split them there")
    lost = sorted(chosen - touched)
    if lost:
        raise ExportError(f"frames {lost[:8]} are not complete frames of any clip (clip ids "
                          f"{sorted({int(clip_of[i]) for i in lost})[:8]})")
    if partial:
        raise ExportError("a Noisebase sequence is a whole clip; --frames covers only part of "
                          + "; ".join(partial[:5]) + ": choose every frame of those clips (--frames all takes "
                          "every clip whole)")
    return whole, split


def _sequence_length(whole: list, split: list) -> int:
    """The frames of every sequence: the whole clips' one length, or without whole clips the run length
    that keeps the most frames (the longer on a tie; 0 when no run has two frames). ExportError for stills
    and whole clips of different lengths."""
    stills = [c for c, idx in whole if len(idx) == 1]
    if stills:
        raise ExportError(f"{len(stills)} of the {len(whole)} clips chosen are stills (clips {stills[:8]}): Noisebase "
                          "sequences are clips of two frames or more; choose the clips (--frames) or export a store "
                          "of clips")
    lengths = sorted({len(idx) for _, idx in whole})
    if len(lengths) > 1:
        by = {n: [c for c, idx in whole if len(idx) == n][:5] for n in lengths}
        raise ExportError(f"the clips chosen have different lengths {by} (length: first clip ids); Noisebase has one "
                          "frames_per_sequence for a dataset: export the clips of one length at a time (--frames)")
    if lengths:
        return lengths[0]
    counts: dict = {}
    for _, runs, _ in split:
        for r in runs:
            if len(r) >= 2:
                counts[len(r)] = counts.get(len(r), 0) + len(r)
    return max(counts, key=lambda k: (counts[k], k)) if counts else 0


def _split_note(c: int, runs: list, cut: list, kept: list, size: int) -> str:
    """The line saying what became of clip ``c``, split at the frames ``cut``."""
    where = f"at its flagged frame{'s' if len(cut) > 1 else ''} {', '.join(map(str, cut[:5]))}"
    if kept:
        rest = [r for r in runs if len(r) != size]
        return (f"clip {c} split {where} into frames {' and '.join(_span(r) for r in kept)}"
                + (f" (frames {', '.join(_span(r) for r in rest)} left out: not {size} frames)" if rest else ""))
    return (f"clip {c} left out {where}: "
            + (f"its frames {', '.join(_span(r) for r in runs)} are no sequence of {size} frames" if runs and size
               else "no run of two frames or more is left" if runs else "no frame is left"))


def render_config_of(store):
    """The :class:`pipeline.render.RenderConfig` the store's frames were rendered with (its recorded config)."""
    from pipeline.errors import PipelineError
    from pipeline.render import RenderConfig
    try:
        cfg = RenderConfig.from_dict(dict(store.config["render"]))          # the resolved settings, res included
    except (PipelineError, ValueError, TypeError, KeyError) as e:
        raise ExportError(f"{store.path}: the recorded dataset config does not give the render settings its samples "
                          f"were drawn with ({e}); the noisebase export re-traces them and needs it") from e
    if cfg.spp != store.layout.spp or tuple(cfg.res) != (store.layout.width, store.layout.height):
        raise ExportError(f"{store.path}: the recorded config renders {cfg.res[0]}x{cfg.res[1]} at {cfg.spp} spp, the "
                          f"store holds {store.layout.width}x{store.layout.height} at {store.layout.spp}")
    return cfg


def frame_geometry(store, i: int, spec, cfg, stored_depth: np.ndarray) -> dict[str, np.ndarray]:
    """The re-traced geometry (:func:`pipeline.render.sample_geometry`) of store frame ``i``, checked
    against its stored per-sample depth (``H x W x S``): at most ``nonfinite_inputs`` samples (those the
    renderer zeroed) may differ by more than the store's rounding."""
    from pipeline.render import FrameScene, sample_geometry
    f = int(store.meta_column("frame")[i])
    geo = sample_geometry(FrameScene(spec, f, cfg))
    d = stored_depth.astype(np.float64)
    off = np.abs(geo["depth"] - d) > DEPTH_SLACK * np.abs(d) + 1e-6
    allowed = int(store.meta_column("nonfinite_inputs")[i])
    if int(off.sum()) > allowed:
        worst = float(np.max(np.abs(geo["depth"] - d)[off]))
        raise ExportError(f"frame {i}: its samples cannot be re-traced: {int(off.sum())} of {off.size} samples' depth "
                          f"differs from the stored one (by up to {worst:.4g}); was the store rendered with other render "
                          "settings or another Mitsuba version? The noisebase export needs the exact samples")
    return geo


def export_noisebase(store, frames: list[int], out: str, name: str = "dataset", left_out=None) -> list[str]:
    """Write the clips of ``frames`` as Noisebase sequences into ``out`` (module docstring; ``left_out``: the
    frames ``--skip-bad-frames`` left out, where clips are split, :func:`clip_sequences`, with one warning
    naming them). Returns the files."""
    import warnings

    import yaml
    from tqdm import tqdm
    clips, notes = clip_sequences(store, frames, left_out)
    if notes:
        warnings.warn("noisebase: " + "; ".join(notes[:5]) + (f" (and {len(notes) - 5} more clips)" if len(notes) > 5
                                                               else ""), stacklevel=2)
    cfg = render_config_of(store)
    lay = store.layout
    files, rows = [], []
    bar = tqdm(total=sum(len(idx) for _, idx in clips), desc="noisebase", unit="frame", dynamic_ncols=True,
               disable=None)
    try:
        for n, (clip, idx) in enumerate(clips):
            fname = f"scene{n:04d}.zip"
            _write_sequence(store, idx, cfg, os.path.join(out, fname), bar)
            files.append(os.path.join(out, fname))
            rows.append({"file": fname, "clip_id": clip, "frames": idx, "split": store.split_of_frame(idx[0]),
                         "scene_seed": int(store.meta_column("scene_seed")[idx[0]])})
    finally:
        bar.close()
    src = {"sequences": len(clips), "files": "scene{index:04d}.zip", "frames_per_sequence": len(clips[0][1]),
           "crop": min(lay.height, lay.width), "samples": lay.spp, "rendering_height": lay.height,
           "rendering_width": lay.width}
    definition = {"name": f"{name} (exported from {os.fspath(store.path)})", "src": src,
                  "flip_rotate": lay.height == lay.width}
    y = os.path.join(out, nb.YAML_NAME)
    with open(y, "w") as f:
        f.write("# A Noisebase sampleset_v1 dataset definition (src: what TrainingSampleLoader_v1 takes; "
                "data_path: this folder)\n")
        yaml.safe_dump(definition, f, sort_keys=False)
    j = os.path.join(out, "sequences.json")
    with open(j, "w") as f:
        json.dump({"format": nb.FORMAT, "store": os.fspath(store.path), "sequences": rows}, f, indent=1)
    return files + [y, j]


def _write_sequence(store, idx: list[int], cfg, path: str, bar) -> None:
    import zarr
    from scene_gen.spec import SceneSpec
    lay = store.layout
    F, H, W, S = len(idx), lay.height, lay.width, lay.spp
    spec = SceneSpec.from_json(store.scene_json(idx[0]))
    zs = zarr.storage.ZipStore(path, mode="w")
    try:
        g = zarr.group(store=zs, zarr_format=2)
        comp = nb.compressor()
        per_sample = {"color": (4, "uint8"), "position": (3, "float32"), "motion": (3, "float32"),
                      "normal": (3, "float16"), "diffuse": (3, "float16")}
        arr = {k: g.create_array(k, shape=(F, c, H, W, S), chunks=(1, c, H, W, min(S, nb.CHUNK_SAMPLES)), dtype=dt,
                                 compressors=comp) for k, (c, dt) in per_sample.items()}
        arr["reference"] = g.create_array("reference", shape=(F, 3, H, W), chunks=(1, 3, H, W), dtype="float32",
                                          compressors=comp)
        small = {"exposure": ((2,), "float32"), "camera_position": ((3,), "float32"),
                 "camera_target": ((3,), "float32"), "camera_up": ((3,), "float32"),
                 "proj_mat": ((4, 4), "float32"), "view_proj_mat": ((4, 4), "float32"), "crop_offset": ((2,), "int32")}
        cols = {k: np.zeros((F,) + shp, dt) for k, (shp, dt) in small.items()}
        gi = FEATURE_GROUPS
        for t, i in enumerate(idx):
            fr = store.read_frame(i, ["radiance", "features", "reference", "camera_to_world", "world_to_clip"])
            feat = fr["features"]                                                 # H W S 17
            geo = frame_geometry(store, i, spec, cfg, feat[..., FEATURE_NAMES.index("depth")])
            to_c = lambda a: np.moveaxis(a, -1, 0)                               # noqa: E731  H W S C -> C H W S
            rng = np.random.default_rng(np.random.SeedSequence([int(spec.seed), int(store.meta_column("frame")[i]),
                                                                RGBE_SALT]))
            rgbe, expo = nb.rgbe_encode(to_c(fr["radiance"]), rng)
            arr["color"][t] = rgbe
            arr["position"][t] = to_c(geo["position"])
            arr["motion"][t] = to_c(geo["motion"])
            arr["normal"][t] = to_c(feat[..., gi["normal"]]).astype(np.float16)
            arr["diffuse"][t] = to_c(feat[..., gi["albedo"]]).astype(np.float16)
            arr["reference"][t] = np.moveaxis(fr["reference"], -1, 0)
            cols["exposure"][t] = expo
            for k, v in nb.camera(fr["camera_to_world"], fr["world_to_clip"]).items():
                cols[k][t] = v
            bar.update(1)
        for k, (shp, dt) in small.items():
            g.create_array(k, shape=(F,) + shp, chunks=(F,) + shp, dtype=dt, compressors=None)[...] = cols[k]
    finally:
        zs.close()
