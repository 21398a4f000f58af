"""``python -m pipeline render-frame``: render one frame of a generated scene to an .npz and a PNG.

    python -m pipeline render-frame --seed S --kind indoor|outdoor --res N [--spp 8] [--ref-spp 4096]
                                    [--frame 0] [--oracle-spp N] [--render-seed N] --out frame.npz

The npz holds ``radiance`` (float32, HWS3), ``features`` (float32, HWS17) with ``feature_names``,
``layers`` (float32, LHW3), ``reference`` and ``reference_stderr`` (float32, HW3), ``guides_albedo``,
``guides_normal``, ``guides_depth``, ``guides_motion``, ``camera_to_world``, ``world_to_clip``,
``scene_json`` (the SceneSpec), ``meta_json`` (the frame's meta as JSON) and, with ``--oracle-spp``,
``oracle`` (float32, HW3): plain ``mi.render`` of the same scene with the same integrator.
Beside it, ``<out>.png`` shows side by side: the input mean, each layer (1, 2, 4, ... spp), the
reference and the oracle, tone-mapped with a fixed curve (log(1 + x), then sRGB; no auto exposure).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError
from core.checks import need


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, required=True, help="scene seed (scene_gen.sampling.sample_scene)")
    from scene_gen.families import family_names
    p.add_argument("--kind", choices=family_names(), required=True, help="scene family")
    p.add_argument("--res", type=int, required=True, help="image width and height in pixels")
    p.add_argument("--spp", type=int, default=8, help="input samples per pixel (default 8)")
    p.add_argument("--ref-spp", type=int, default=4096, help="reference samples per pixel (default 4096)")
    p.add_argument("--frame", type=int, default=0, help="frame index in the clip (default 0)")
    p.add_argument("--num-frames", type=int, default=None,
                   help="clip length of the generated scene (default: frame + 1)")
    p.add_argument("--oracle-spp", type=int, default=0,
                   help="also render plain mi.render at this spp as 'oracle' (default 0: none)")
    p.add_argument("--layers", type=int, default=6, help="sample layers of 1, 2, ... 2**(L-1) spp (default 6)")
    p.add_argument("--ref-passes", type=int, default=None,
                   help="reference passes (default: 32, or 16 for small --ref-spp): a stop lands on a whole pass; "
                        "with --reference batch_means, the batches of the standard error")
    p.add_argument("--ref-target", type=float, default=None,
                   help="stop the reference early once its relative standard error is below this")
    p.add_argument("--render-seed", type=int, default=0,
                   help="the samples' seed, apart from the scene's: two renders of one scene with different "
                        "render seeds are independent (default 0, the dataset's)")
    from pipeline.render import REFERENCE_METHODS
    p.add_argument("--reference", choices=REFERENCE_METHODS, default="moments",
                   help="moments (default): per-pixel second moments in each launch, shutter times by the "
                        "frame's motion; batch_means: --ref-passes passes and their batch means")
    p.add_argument("--ref-times", type=int, default=0,
                   help="distinct shutter times of a moving frame's reference (default 0: by its motion); "
                        "e.g. 256 with --ref-passes 2 for a dense-time reference")
    p.add_argument("--threads", type=int, default=0, help="drjit threads (default: all cores)")
    p.add_argument("--out", required=True, help="output .npz path (a .png is written beside it)")


def _config(args):
    from pipeline.render import RenderConfig
    need(args.render_seed >= 0, "--render-seed", "an integer >= 0", args.render_seed, ConfigError)
    passes = args.ref_passes
    if passes is None:
        passes = 32 if args.ref_spp >= 32 * 16 else 16
    need(not args.ref_spp or args.ref_spp % passes == 0, "--ref-spp",
         f"a multiple of the number of reference passes ({passes})", args.ref_spp, ConfigError)
    return RenderConfig(res=(args.res, args.res) if args.res > 0 else args.res, spp=args.spp,
                        layer_levels=args.layers, ref_spp=args.ref_spp, ref_passes=passes,
                        ref_min_passes=min(16, passes), ref_target_rel_stderr=args.ref_target,
                        threads=args.threads, oracle_spp=args.oracle_spp, seed_offset=args.render_seed,
                        reference=args.reference, ref_times=args.ref_times)


def panel_image(out: dict) -> np.ndarray:
    """Input mean, layers, reference, oracle side by side (float32, H × (n·(W+2) - 2) × 3), linear HDR."""
    panels = [out["radiance"].mean(axis=2)] + list(out["layers"]) + [out["reference"]]
    if "oracle" in out:
        panels.append(out["oracle"])
    h = panels[0].shape[0]
    gap = np.zeros((h, 2, 3), np.float32)
    row = []
    for i, p in enumerate(panels):
        if i:
            row.append(gap)
        row.append(np.asarray(p, np.float32))
    return np.concatenate(row, axis=1)


def write_npz(path: Path, out: dict, feature_names) -> None:
    arrays = {k: v for k, v in out.items() if k != "meta"}
    arrays["feature_names"] = np.array(feature_names)
    arrays["scene_json"] = np.array(out["meta"]["scene_json"])
    arrays["meta_json"] = np.array(json.dumps(out["meta"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


def run(args) -> int:
    from pipeline.render import render_frame
    from core.images import write_png
    from scene_gen.sampling import sample_scene
    from stores.contract import FEATURE_NAMES

    out_path = Path(args.out)
    if out_path.suffix != ".npz":
        raise ConfigError(f"--out must end in .npz, got {args.out!r}")
    need(args.res > 0, "--res", "a positive number of pixels", args.res, ConfigError)
    need(args.frame >= 0, "--frame", ">= 0", args.frame, ConfigError)
    num_frames = args.num_frames if args.num_frames is not None else args.frame + 1
    if args.frame >= num_frames:
        raise ConfigError(f"--frame {args.frame} is outside a clip of --num-frames {num_frames}")
    cfg = _config(args)
    spec = sample_scene(args.seed, args.kind, num_frames=num_frames, res=args.res)
    out = render_frame(spec, args.frame, cfg)
    write_npz(out_path, out, FEATURE_NAMES)
    png = out_path.with_suffix(".png")
    write_png(png, panel_image(out), exposure=1.0, mode="log")
    m = out["meta"]
    print(f"wrote {out_path} and {png}: {args.kind} seed {args.seed} frame {args.frame}, {args.res}x{args.res}, "
          f"{cfg.spp} spp, {len(spec.objects)} objects, motion={m['has_motion']}, defocus={m['has_defocus']}, "
          f"reference {m['reference_spp']} spp (rel. stderr {m['reference_rel_stderr']:.4f}, "
          f"ref_time_slices {m['ref_time_slices']}), "
          f"non-finite {m['nonfinite_inputs']}/{m['nonfinite_layers']}/{m['nonfinite_reference']}, "
          f"{m['render_seconds']:.1f} s")
    return 0
