"""The data contract between the renderer (pipeline.render) and the store (stores.writer).

Plain data, no imports. A rendered frame is a plain dict (``pipeline.render.render_frame``,
``pipeline.render.assemble``): one numpy array for every name of :data:`FRAME_ARRAYS`, of the shape
and dtype given there, plus ``meta``, a dict with the keys and types of :data:`FRAME_META`. The store
writer (``stores.writer.StoreWriter.write_frame``), the schema's array table and the exports use these
names. Shapes use H, W (pixels), S (samples per pixel, default 8) and L = number of sample layers
(6: 1, 2, 4, 8, 16, 32 spp).
"""
from __future__ import annotations

# Per-sample feature channels, in order (17 floats; with radiance's 3 that is 20 floats a sample).
FEATURE_NAMES: tuple[str, ...] = (
    "normal_x", "normal_y", "normal_z",        # world-space shading normal at the primary hit (0 on a miss)
    "depth",                                   # distance along the ray to the primary hit (0 on a miss)
    "albedo_r", "albedo_g", "albedo_b",        # diffuse reflectance at the primary hit, in [0, 1]
    "specular_r", "specular_g", "specular_b",  # specular colour of the hit material (per-shape table)
    "roughness",                               # roughness of the hit material in [0, 1]
    "motion_x", "motion_y",                    # screen-space motion in pixels to the previous frame: p_prev - p_cur
    "coc",                                     # signed circle of confusion in pixels (0 at the focus distance)
    "lens_u", "lens_v",                        # lens position on the unit disk (0 without defocus)
    "time",                                    # time of the sample within the shutter, in [0, 1)
)
NUM_FEATURES = len(FEATURE_NAMES)
FEATURE_GROUPS = {
    "normal": slice(0, 3), "depth": slice(3, 4), "albedo": slice(4, 7), "specular": slice(7, 10),
    "roughness": slice(10, 11), "motion": slice(11, 13), "coc": slice(13, 14), "lens": slice(14, 16),
    "time": slice(16, 17),
}
LAYER_SPP: tuple[int, ...] = (1, 2, 4, 8, 16, 32)   # sample layer n holds the mean of 2**n samples

# name -> (shape template, dtype). Images are channel-last (H, W, C) as rendered.
FRAME_ARRAYS = {
    "radiance": (("H", "W", "S", 3), "float32"),
    "features": (("H", "W", "S", NUM_FEATURES), "float32"),
    "layers": (("L", "H", "W", 3), "float32"),
    "reference": (("H", "W", 3), "float32"),
    "reference_stderr": (("H", "W", 3), "float32"),
    "guides_albedo": (("H", "W", 3), "float32"),
    "guides_normal": (("H", "W", 3), "float32"),
    "guides_depth": (("H", "W", 1), "float32"),
    "guides_motion": (("H", "W", 2), "float32"),
    "camera_to_world": ((4, 4), "float64"),
    "world_to_clip": ((4, 4), "float64"),      # projection * view of this frame (NDC in [-1, 1])
}
# Scalars / strings recorded per frame (a rendered frame's ``meta`` dict):
FRAME_META = {
    "scene_json": str,          # SceneSpec JSON (scene_gen.spec)
    "scene_seed": int,
    "frame": int,               # index of the frame in its clip
    "num_frames": int,          # clip length (1 for a still)
    "has_motion": bool,
    "has_defocus": bool,
    "nonfinite_inputs": int,    # NaN/Inf samples replaced in radiance/features
    "nonfinite_layers": int,
    "nonfinite_reference": int,
    "reference_spp": int,       # samples actually taken for the reference (early stop may cut it)
    "reference_rel_stderr": float,  # achieved mean relative standard error of the reference
    "render_seconds": float,
    "case": str,                # hard cases of the scene (scene_gen.cases), comma-separated; '' for ordinary frames
    "ref_time_slices": int,     # distinct shutter times of the reference (1: static; 0: not recorded, older stores)
    "kind": str,                # the scene family (scene_gen.families: 'indoor', 'outdoor', ...); '' in older stores
    "nonfinite_expected": bool,  # NaN/Inf samples are the purpose of the frame's hard case (scene_gen.cases.Case)
}
