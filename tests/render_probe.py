"""Test helpers that look inside the renderer: one wavefront traced and read back with its primary hits
(``trace``), the per-shape table index of hit shapes (``shape_index``) and the shapes a frame's arrays must
have (``expected_shapes``). The renderer itself carries none of this (its kernel takes a ``probe``)."""
from __future__ import annotations

import numpy as np

from stores.contract import FRAME_ARRAYS, NUM_FEATURES


def trace(fs, seed: int, row0: int, rows: int, s_per: int, t: float, *, debug: bool = False) -> dict:
    """One wavefront, read back: ``rows`` pixel rows from ``row0``, ``s_per`` samples a pixel, at shutter
    time ``t`` (the scene already there). Returns numpy arrays of N = rows·W·s_per lanes (pixel-major,
    then sample): ``L`` (float32, N×3, radiance times the ray weight) and ``F`` (float32, N×17, the
    features), both after the NaN/Inf rule. ``debug``: also the primary hit point ``p``, ray direction
    ``d``, film position ``film`` (in [0, 1]²), ``hit``, the hit shape's registry id ``sid``, shading
    normal ``n``, ray distance ``t``, diffuse reflectance ``albedo`` and lens sample on the unit disk
    ``lens``, computed in the wavefront's own kernel."""
    from pipeline.render import inputs as I

    def probe(prim, ray, film, ap):
        return dict(p=prim["p"], d=ray.d, film=film, hit=prim["hit"], sid=prim["shape"], n=prim["n"], t=prim["t"],
                    albedo=prim["albedo"], lens=fs.mi.warp.square_to_uniform_disk_concentric(ap))

    n = rows * fs.cfg.width * s_per
    buf, _cols, extra = I._wave(fs, seed, I._wave_params(fs, row0, t), rows, s_per, probe=probe if debug else None)
    a = I._read(buf).view(np.float32)
    out = {"L": a[:3 * n].reshape(n, 3), "F": a[3 * n:].reshape(n, NUM_FEATURES)}
    for k, v in extra.items():
        a = np.asarray(v)
        out[k] = a.T if a.ndim == 2 and a.shape[0] in (2, 3) and a.shape[1] == n else a
    return out


def shape_index(fs, registry_ids) -> np.ndarray:
    """Index into ``fs``'s per-shape tables (int64, 0 = no hit) of drjit shape registry ids (0 = no hit)."""
    ids = np.asarray(registry_ids, np.int64)
    known = fs.shape_registry_ids
    if len(known) == 0:
        return np.zeros(ids.shape, np.int64)
    order = np.argsort(known)
    pos = np.clip(np.searchsorted(known[order], ids), 0, len(known) - 1)
    found = (known[order][pos] == ids) & (ids != 0)
    return np.where(found, order[pos] + 1, 0)


def expected_shapes(cfg) -> dict[str, tuple[tuple[int, ...], str]]:
    """``FRAME_ARRAYS`` with H, W, S, L filled in for a ``RenderConfig``."""
    dims = {"H": cfg.height, "W": cfg.width, "S": cfg.spp, "L": cfg.layer_levels}
    return {k: (tuple(dims.get(d, d) for d in shape), dtype) for k, (shape, dtype) in FRAME_ARRAYS.items()}


def camera_depth(cam, pts: np.ndarray) -> np.ndarray:
    """Camera-space z (float64, N) of world points: distance along the view axis."""
    from scene_gen.projection import camera_to_world
    c2w = camera_to_world(cam)
    p = np.asarray(pts, np.float64)
    o, f = c2w[:3, 3], c2w[:3, 2]
    return (p[..., 0] - o[0]) * f[0] + (p[..., 1] - o[1]) * f[1] + (p[..., 2] - o[2]) * f[2]
