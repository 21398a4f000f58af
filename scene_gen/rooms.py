"""Procedural rooms: floor plans, room meshes with openings, and indoor scene layout.

A room is a union of axis-aligned rectangles in the x-z plane (metres, floor at y = 0, +y up) with a
ceiling at ``height``. Its walls are the boundary of that union, found on the grid of rectangle
edges and merged into straight runs, listed in a fixed order (:func:`room_walls`), so an opening is
``[wall_index, u0, u1, v0, v1]``: metres along the wall from its start and above the floor.

``build_room_mesh(params)`` (``MeshSpec(kind='room', params=...)``) makes one part of the room,
``params['part']`` in ``floor | walls | ceiling``, with faces that look *into* the room (a camera
inside sees the front side), holes where the openings and ``skylights`` are, UVs in metres and flat
normals. Meshes are in world units and are not normalised.

Room types (:data:`ROOM_TYPES`, >= 8): box, long, L, T, U, cross, hall (with pillars), loft (skylights),
studio (one glazed wall). :func:`layout_indoor` places the room, furniture (tables and shelves with
objects on them), loose objects on the floor, four area lights (emissive rectangles under the ceiling),
one point light and an environment probe seen through the windows.
"""
from __future__ import annotations

import math

import numpy as np

from scene_gen.errors import MeshError, SpecError
from scene_gen.layout import Layout, Placed, light_color, probe_params, random_shape, register_family, upright

ROOM_TYPES = ("box", "long", "L", "T", "U", "cross", "hall", "loft", "studio")
PARTS = ("floor", "walls", "ceiling")


def _f(x) -> float:
    return round(float(x), 4)


# ---------------------------------------------------------------------------------------------
# floor plans

def _grid(rects: np.ndarray):
    xs = np.unique(np.concatenate([rects[:, 0], rects[:, 2]]))
    zs = np.unique(np.concatenate([rects[:, 1], rects[:, 3]]))
    cx = (xs[:-1] + xs[1:]) / 2
    cz = (zs[:-1] + zs[1:]) / 2
    inside = np.zeros((len(cx), len(cz)), bool)
    for x0, z0, x1, z1 in rects:
        inside |= ((cx[:, None] > x0) & (cx[:, None] < x1)) & ((cz[None, :] > z0) & (cz[None, :] < z1))
    return xs, zs, inside


def _check_rects(rects) -> np.ndarray:
    try:
        r = np.asarray(rects, np.float64)
    except (TypeError, ValueError):
        r = np.zeros((0,))
    if r.ndim != 2 or r.shape[1] != 4 or len(r) == 0 or not np.isfinite(r).all() \
            or (r[:, 2] <= r[:, 0]).any() or (r[:, 3] <= r[:, 1]).any():
        raise SpecError(f"mesh.params.rects (room) must be a list of [x0, z0, x1, z1] with x0 < x1, z0 < z1, got {rects!r}")
    return r


def room_walls(rects) -> list[tuple[tuple[float, float], tuple[float, float], tuple[float, float]]]:
    """Walls of the union of ``rects`` ([[x0, z0, x1, z1], ...]) as (start, end, inward normal) in x-z.

    Each wall is a maximal straight run of the boundary; the order is fixed (x-normal walls by x then z,
    then z-normal walls by z then x), so wall indices are stable."""
    r = _check_rects(rects)
    xs, zs, inside = _grid(r)
    nx, nz = inside.shape
    walls = []
    # walls on lines x = xs[i] (normals ±x)
    for i in range(nx + 1):
        left = inside[i - 1] if i > 0 else np.zeros(nz, bool)
        right = inside[i] if i < nx else np.zeros(nz, bool)
        side = np.where(left != right, np.where(right, 1, -1), 0)  # +1: room on +x side
        j = 0
        while j < nz:
            if side[j] == 0:
                j += 1
                continue
            k = j
            while k + 1 < nz and side[k + 1] == side[j]:
                k += 1
            walls.append(((xs[i], zs[j]), (xs[i], zs[k + 1]), (float(side[j]), 0.0)))
            j = k + 1
    for j in range(nz + 1):
        below = inside[:, j - 1] if j > 0 else np.zeros(nx, bool)
        above = inside[:, j] if j < nz else np.zeros(nx, bool)
        side = np.where(below != above, np.where(above, 1, -1), 0)
        i = 0
        while i < nx:
            if side[i] == 0:
                i += 1
                continue
            k = i
            while k + 1 < nx and side[k + 1] == side[i]:
                k += 1
            walls.append(((xs[i], zs[j]), (xs[k + 1], zs[j]), (0.0, float(side[i]))))
            i = k + 1
    return [((float(a[0]), float(a[1])), (float(b[0]), float(b[1])), n) for a, b, n in walls]


def inside_plan(rects, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Whether x-z ``points`` (N×2) lie inside the union of ``rects`` at least ``margin`` from every wall (bool, N)."""
    r = np.asarray(rects, np.float64)
    p = np.atleast_2d(np.asarray(points, np.float64))

    def inside(q):
        ok = np.zeros(len(q), bool)
        for x0, z0, x1, z1 in r:
            ok |= (q[:, 0] > x0) & (q[:, 0] < x1) & (q[:, 1] > z0) & (q[:, 1] < z1)
        return ok

    ok = inside(p)
    if margin > 0:
        for dx, dz in ((1, 0), (-1, 0), (0, 1), (0, -1), (0.7, 0.7), (0.7, -0.7), (-0.7, 0.7), (-0.7, -0.7)):
            ok &= inside(p + margin * np.array([dx, dz]))
    return ok


def random_plan(rng: np.random.Generator, room_type: str) -> dict:
    """A room's ``rects`` (list of [x0, z0, x1, z1]), ``height`` and ``pillars`` ([[x, z, half_size]])."""
    u = rng.uniform
    pillars = []
    if room_type == "box":
        w, d, h = u(4.0, 7.0), u(3.5, 6.0), u(2.6, 3.2)
        rects = [[-w / 2, -d / 2, w / 2, d / 2]]
    elif room_type == "long":
        w, d, h = u(8.0, 12.0), u(2.6, 3.6), u(2.6, 3.0)
        rects = [[-w / 2, -d / 2, w / 2, d / 2]]
    elif room_type == "L":
        w, d, h = u(6.0, 9.0), u(5.0, 8.0), u(2.6, 3.2)
        a, b = u(0.35, 0.55) * w, u(0.35, 0.55) * d
        rects = [[-w / 2, -d / 2, w / 2, -d / 2 + b], [-w / 2, -d / 2, -w / 2 + a, d / 2]]
    elif room_type == "T":
        w, d, h = u(8.0, 11.0), u(6.0, 8.0), u(2.7, 3.3)
        bar, stem = u(2.8, 3.8), u(2.8, 4.0)
        rects = [[-w / 2, d / 2 - bar, w / 2, d / 2], [-stem / 2, -d / 2, stem / 2, d / 2 - bar + 0.01]]
    elif room_type == "U":
        w, d, h = u(7.0, 10.0), u(6.0, 8.0), u(2.6, 3.2)
        arm, base = u(2.5, 3.2), u(2.5, 3.2)
        rects = [[-w / 2, -d / 2, w / 2, -d / 2 + base], [-w / 2, -d / 2, -w / 2 + arm, d / 2],
                 [w / 2 - arm, -d / 2, w / 2, d / 2]]
    elif room_type == "cross":
        w, d, h = u(7.0, 10.0), u(7.0, 10.0), u(2.8, 3.4)
        a, b = u(2.8, 3.8), u(2.8, 3.8)
        rects = [[-w / 2, -b / 2, w / 2, b / 2], [-a / 2, -d / 2, a / 2, d / 2]]
    elif room_type == "hall":
        w, d, h = u(10.0, 14.0), u(8.0, 12.0), u(4.0, 6.0)
        rects = [[-w / 2, -d / 2, w / 2, d / 2]]
        nx = int(rng.integers(2, 4))
        s = u(0.15, 0.3)
        for i in range(nx):
            x = -w / 2 + w * (i + 1) / (nx + 1)
            for z in (-d / 4, d / 4):
                pillars.append([_f(x), _f(z), _f(s)])
    elif room_type == "loft":
        w, d, h = u(6.0, 9.0), u(5.0, 7.0), u(3.5, 4.5)
        rects = [[-w / 2, -d / 2, w / 2, d / 2]]
    elif room_type == "studio":
        w = u(5.0, 7.0)
        d, h = w * u(0.8, 1.1), u(3.0, 3.6)
        rects = [[-w / 2, -d / 2, w / 2, d / 2]]
    else:
        raise SpecError(f"room type must be one of {ROOM_TYPES}, got {room_type!r}")
    return {"rects": [[_f(c) for c in r] for r in rects], "height": _f(h), "pillars": pillars}


def random_openings(rng: np.random.Generator, room_type: str, rects, height: float) -> tuple[list, list]:
    """Windows and doors (``[wall, u0, u1, v0, v1]``) and skylights (``[x0, z0, x1, z1]``) for a plan.

    Every room gets at least two windows so the environment probe lights it."""
    walls = room_walls(rects)
    lengths = [math.dist(a, b) for a, b, _ in walls]
    order = np.argsort(-np.asarray(lengths), kind="stable")
    openings = []
    if room_type == "studio":  # one glazed wall: a band of tall windows over the longest wall
        i = int(order[0])
        L = lengths[i]
        n = max(2, int(L // 1.6))
        seg = L / n
        for k in range(n):
            openings.append([i, _f(k * seg + 0.12), _f((k + 1) * seg - 0.12), 0.4, _f(height - 0.3)])
    # windows on the longer walls (at most 2 per wall), never closer than 0.4 m to a corner
    n_win = int(rng.integers(2, 5))
    candidates = [int(i) for i in order if lengths[int(i)] >= 1.6]
    for i in candidates[: max(2, len(candidates) // 2 + 1)]:
        if n_win <= 0:
            break
        L = lengths[i]
        if room_type == "studio" and i == int(order[0]):
            continue
        per_wall = 2 if L > 5.0 else 1
        slots = np.linspace(0, L, per_wall + 1)
        for s0, s1 in zip(slots[:-1], slots[1:]):
            if n_win <= 0:
                break
            ww = min(rng.uniform(0.8, 2.0), s1 - s0 - 0.9)
            if ww < 0.5:
                continue
            c = rng.uniform(s0 + 0.4 + ww / 2, s1 - 0.4 - ww / 2)
            v0 = rng.uniform(0.7, 1.0)
            v1 = min(height - 0.25, v0 + rng.uniform(1.0, 1.6))
            openings.append([i, _f(c - ww / 2), _f(c + ww / 2), _f(v0), _f(v1)])
            n_win -= 1
    # a door on a wall without windows when there is one
    used = {o[0] for o in openings}
    free = [int(i) for i in order if int(i) not in used and lengths[int(i)] >= 1.4]
    if free and rng.uniform() < 0.7:
        i = free[int(rng.integers(len(free)))]
        c = rng.uniform(0.6, lengths[i] - 0.6)
        openings.append([i, _f(c - 0.45), _f(c + 0.45), 0.0, _f(min(2.1, height - 0.2))])
    skylights = []
    if room_type in ("loft", "hall") or rng.uniform() < 0.15:
        r = np.asarray(rects, float)[0]
        n = int(rng.integers(1, 4))
        for k in range(n):
            cx = r[0] + (r[2] - r[0]) * (k + 1) / (n + 1)
            cz = rng.uniform(r[1] + 1.0, r[3] - 1.0) if r[3] - r[1] > 2.5 else (r[1] + r[3]) / 2
            sx, sz = rng.uniform(0.4, 0.7), rng.uniform(0.5, 1.0)
            skylights.append([_f(cx - sx), _f(cz - sz), _f(cx + sx), _f(cz + sz)])
    return openings, skylights


# ---------------------------------------------------------------------------------------------
# mesh

def _quads(corners: np.ndarray, normal: np.ndarray, uvs: np.ndarray):
    """corners (Q×4×3, counter-clockwise seen from the normal side), uvs (Q×4×2) -> v, f, n, uv."""
    q = len(corners)
    v = corners.reshape(-1, 3)
    base = 4 * np.arange(q)[:, None]
    f = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.int32)
    n = np.broadcast_to(normal, (len(v), 3)).copy()
    return v, f, n, uvs.reshape(-1, 2)


def _cells(xs, zs, keep) -> np.ndarray:
    i, j = np.nonzero(keep)
    return np.stack([xs[i], zs[j], xs[i + 1], zs[j + 1]], axis=1)


def _floor_or_ceiling(rects, height, skylights, part):
    r = _check_rects(rects)
    holes = np.asarray(skylights, np.float64).reshape(-1, 4) if part == "ceiling" else np.zeros((0, 4))
    xs = np.unique(np.concatenate([r[:, 0], r[:, 2], holes[:, 0], holes[:, 2]]))
    zs = np.unique(np.concatenate([r[:, 1], r[:, 3], holes[:, 1], holes[:, 3]]))
    cx, cz = (xs[:-1] + xs[1:]) / 2, (zs[:-1] + zs[1:]) / 2
    pts = np.stack(np.meshgrid(cx, cz, indexing="ij"), -1).reshape(-1, 2)
    keep = inside_plan(r, pts).reshape(len(cx), len(cz))
    for x0, z0, x1, z1 in holes:
        keep &= ~(((cx[:, None] > x0) & (cx[:, None] < x1)) & ((cz[None, :] > z0) & (cz[None, :] < z1)))
    c = _cells(xs, zs, keep)
    y = 0.0 if part == "floor" else float(height)
    x0, z0, x1, z1 = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
    if part == "floor":   # +y: (x0,z0) (x0,z1) (x1,z1) (x1,z0) is counter-clockwise seen from above
        xz = np.stack([np.stack([x0, z0], 1), np.stack([x0, z1], 1), np.stack([x1, z1], 1), np.stack([x1, z0], 1)], 1)
        normal = np.array([0.0, 1.0, 0.0])
    else:
        xz = np.stack([np.stack([x0, z0], 1), np.stack([x1, z0], 1), np.stack([x1, z1], 1), np.stack([x0, z1], 1)], 1)
        normal = np.array([0.0, -1.0, 0.0])
    corners = np.concatenate([xz[..., :1], np.full(xz.shape[:2] + (1,), y), xz[..., 1:]], axis=-1)
    return _quads(corners, normal, xz.copy())


def _walls(rects, height, openings):
    walls = room_walls(rects)
    ops = np.asarray(openings, np.float64).reshape(-1, 5)
    if len(ops) and ((ops[:, 0] < 0) | (ops[:, 0] >= len(walls)) | (ops[:, 0] % 1 != 0)).any():
        raise SpecError(f"mesh.params.openings (room): wall index out of range [0, {len(walls) - 1}]")
    all_v, all_f, all_n, all_uv = [], [], [], []
    off = 0
    u_start = 0.0
    for w, (a, b, nin) in enumerate(walls):
        a, b = np.asarray(a), np.asarray(b)
        L = float(np.linalg.norm(b - a))
        t = (b - a) / L
        mine = ops[ops[:, 0] == w]
        us = np.unique(np.clip(np.concatenate([[0.0, L], mine[:, 1], mine[:, 2]]), 0.0, L))
        vs = np.unique(np.clip(np.concatenate([[0.0, height], mine[:, 3], mine[:, 4]]), 0.0, height))
        cu, cv = (us[:-1] + us[1:]) / 2, (vs[:-1] + vs[1:]) / 2
        keep = np.ones((len(cu), len(cv)), bool)
        for _, u0, u1, v0, v1 in mine:
            keep &= ~(((cu[:, None] > u0) & (cu[:, None] < u1)) & ((cv[None, :] > v0) & (cv[None, :] < v1)))
        c = _cells(us, vs, keep)
        if len(c) == 0:
            continue
        u0, v0, u1, v1 = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
        uv = np.stack([np.stack([u0, v0], 1), np.stack([u1, v0], 1), np.stack([u1, v1], 1), np.stack([u0, v1], 1)], 1)
        n3 = np.array([nin[0], 0.0, nin[1]])
        # cross(t, up) = (-tz, 0, tx): that is the normal of the (u0,v0) (u1,v0) (u1,v1) order
        if np.dot([-t[1], t[0]], nin) < 0:
            uv = uv[:, ::-1]
        xz = a[None, None, :] + uv[..., :1] * t[None, None, :]
        corners = np.concatenate([xz[..., :1], uv[..., 1:], xz[..., 1:]], axis=-1)
        v, f, n, tex = _quads(corners, n3, uv + [u_start, 0.0])
        all_v.append(v), all_f.append(f + off), all_n.append(n), all_uv.append(tex)
        off += len(v)
        u_start += L
    return (np.concatenate(all_v), np.concatenate(all_f), np.concatenate(all_n), np.concatenate(all_uv))


def build_room_mesh(params: dict):
    """One part of a room (``params``: ``rects``, ``height``, ``openings``, ``skylights``, ``part``) as MeshData.

    Faces look into the room; vertices are in metres (not normalised); UVs are metres along the surface."""
    from scene_gen.meshes import MeshData

    part = params.get("part", "walls")
    if part not in PARTS:
        raise SpecError(f"mesh.params.part (room) must be one of {PARTS}, got {part!r}")
    h = params.get("height", 3.0)
    if isinstance(h, bool) or not isinstance(h, (int, float)) or not (0.5 <= h <= 100):
        raise SpecError(f"mesh.params.height (room) must be a number in [0.5, 100] metres, got {h!r}")
    rects = params.get("rects")
    if part == "walls":
        v, f, n, uv = _walls(rects, float(h), params.get("openings", []))
    else:
        v, f, n, uv = _floor_or_ceiling(rects, float(h), params.get("skylights", []), part)
    if len(f) == 0:
        raise MeshError(f"room part {part!r} has no faces (params {params!r})")
    return MeshData(vertices=v, faces=f, normals=n, uv=uv)


# ---------------------------------------------------------------------------------------------
# indoor layout

# Radiance scales chosen so a 64-spp preview with the fixed log tone map is well exposed.
AREA_POWER = (1.5, 6.0)       # radiance x area of each emissive rectangle (log-uniform)
POINT_INTENSITY = (1.0, 6.0)  # point light intensity (log-uniform)
INDOOR_SKY = (0.8, 2.5)       # probe sky radiance seen through the windows (log-uniform)
INDOOR_SUN = 8.0              # probe sun irradiance: sunlit patches through windows stand out


def _logu(rng, lo_hi) -> float:
    return math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1])))


def _clamp_into(rects, height, margin=0.35):
    r = np.asarray(rects, np.float64)

    def clamp(p):
        p = np.asarray(p, np.float64).copy()
        p[1] = np.clip(p[1], 0.2, height - 0.2)
        if inside_plan(r, p[[0, 2]][None], margin)[0]:
            return p
        best, bd = None, np.inf
        for x0, z0, x1, z1 in r:
            q = np.array([np.clip(p[0], x0 + margin, x1 - margin), np.clip(p[2], z0 + margin, z1 - margin)])
            d = np.linalg.norm(q - p[[0, 2]])
            if d < bd:
                best, bd = q, d
        p[0], p[2] = best
        return p
    return clamp


def _sample_in_plan(rng, rects, margin, n_try=4):
    r = np.asarray(rects, np.float64)
    lo, hi = r[:, :2].min(0), r[:, 2:].max(0)
    for _ in range(n_try):   # batches of candidates; the first inside one wins
        p = rng.uniform(lo, hi, (32, 2))
        ok = np.flatnonzero(inside_plan(r, p, margin))
        if len(ok):
            return p[ok[0]]
    c = r[0]
    return np.array([(c[0] + c[2]) / 2, (c[1] + c[3]) / 2])


@register_family("indoor")
def layout_indoor(rng: np.random.Generator, r_cam: np.random.Generator, cfg, fov: float, res: int,
                  user_models: list[str]):
    """Room, furniture, ~``cfg.indoor_objects`` meshes, 4 area lights, 1 point light, 1 probe (a ``scene_gen.layout.Layout``)."""
    from scene_gen.materials import diffuse, random_color, random_material, random_texture
    from scene_gen.spec import LightSpec, MaterialSpec, MeshSpec, Transform

    room_type = ROOM_TYPES[int(rng.integers(len(ROOM_TYPES)))]
    plan = random_plan(rng, room_type)
    rects, H = plan["rects"], plan["height"]
    openings, skylights = random_openings(rng, room_type, rects, H)
    base = {"rects": rects, "height": H, "openings": openings, "skylights": skylights, "type": room_type}
    objects = []
    # room surfaces
    ftex = random_texture(rng, kind=("checker", "stripes", "noise", "cells")[int(rng.integers(4))])
    floor_mat = (MaterialSpec("roughplastic", base_color=ftex.color0, specular_color=(0.04, 0.04, 0.04),
                              roughness=0.4, params={"int_ior": 1.5}, texture=ftex)
                 if rng.uniform() < 0.5 else diffuse(ftex.color0, texture=ftex))
    wall_c = random_color(rng, v_range=(0.65, 0.95), s_max=0.35)
    wall_mat = diffuse(wall_c, texture=random_texture(rng, wall_c, kind="stripes") if rng.uniform() < 0.25 else None)
    ceil_mat = diffuse(random_color(rng, v_range=(0.8, 0.95), s_max=0.1))
    for part, mat in (("floor", floor_mat), ("walls", wall_mat), ("ceiling", ceil_mat)):
        objects.append(Placed(f"room_{part}", MeshSpec("room", {**base, "part": part}), mat, Transform(),
                              radius=1e3, keep=True, movable=False, budget=False))
    for i, (x, z, s) in enumerate(plan["pillars"]):
        objects.append(Placed(f"pillar_{i}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), wall_mat,
                              Transform((x, _f(H / 2), z), (0, 0, 0), (_f(s), _f(H / 2), _f(s))),
                              radius=math.hypot(s * 1.5, H / 2), movable=False))

    # camera: near the boundary, looking across the room with a clear line of sight
    clamp = _clamp_into(rects, H)
    origin = target = None
    best = -1.0
    for _ in range(200):   # the longest of a few clear sight lines: views across the room
        o = _sample_in_plan(r_cam, rects, 0.4)
        t = _sample_in_plan(r_cam, rects, 0.3)
        dist = float(np.linalg.norm(t - o))
        if dist < 2.2 or dist <= best:
            continue
        line = o[None] + np.linspace(0, 1, 24)[:, None] * (t - o)[None]
        if not inside_plan(rects, line, 0.1).all():
            continue
        best = dist
        # the target is low (the floor near it is in view); the eye at standing or sitting height
        origin = np.array([o[0], r_cam.uniform(1.1, min(1.9, H - 0.4)), o[1]])
        target = np.array([t[0], r_cam.uniform(0.1, 0.7), t[1]])
        if best > 4.0:
            break
    if origin is None:  # pragma: no cover - every plan has a 2.2 m line of sight
        origin, target = np.array([0.0, 1.5, 0.0]), np.array([1.0, 0.8, 1.0])
    cam0 = cams_make(origin, target, fov)

    from scene_gen.cameras import frustum_test
    in_view = frustum_test(cam0, (res, res))
    tan_x = math.tan(math.radians(fov) / 2)
    from scene_gen.cameras import basis
    rt, up_, fw = basis(cam0)

    n_total = cfg.indoor_objects
    count = [0]
    supports = []   # (x, z, y_top, half_x, half_z, yaw) surfaces to put things on

    def add(name, mesh, mat, t, radius, **kw):
        objects.append(Placed(name, mesh, mat, t, radius=radius, **kw))
        count[0] += 1

    # tables
    wood = random_material(rng, kind=("diffuse", "roughplastic", "principled")[int(rng.integers(3))])
    for ti in range(int(rng.integers(0, 3))):
        if count[0] + 3 > n_total:
            break
        hx, hz, ht = rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.5), rng.uniform(0.68, 0.78)
        for _ in range(30):
            p = _sample_in_plan(rng, rects, max(hx, hz) + 0.3)
            if in_view([p[0], ht / 2, p[1]], max(hx, hz)) or rng.uniform() < 0.1:
                break
        yaw = rng.uniform(0, 360)
        add(f"table{ti}_top", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), wood,
            Transform((_f(p[0]), _f(ht - 0.02), _f(p[1])), (0.0, _f(yaw), 0.0), (_f(hx), 0.02, _f(hz))),
            radius=math.hypot(hx, hz), movable=False)
        add(f"table{ti}_leg", MeshSpec("cylinder", {"radius": 1.0, "height": 2.0, "sections": 24}), wood,
            Transform((_f(p[0]), _f((ht - 0.04) / 2), _f(p[1])), (0.0, 0.0, 0.0), (0.06, _f((ht - 0.04) / 2), 0.06)),
            radius=ht / 2, movable=False)
        add(f"table{ti}_foot", MeshSpec("cylinder", {"radius": 1.0, "height": 2.0, "sections": 24}), wood,
            Transform((_f(p[0]), 0.02, _f(p[1])), (0.0, 0.0, 0.0), (_f(min(hx, hz) * 0.7), 0.02, _f(min(hx, hz) * 0.7))),
            radius=min(hx, hz), movable=False)
        supports.append((p[0], p[1], ht, hx * 0.85, hz * 0.85, yaw))
    # shelves against long walls
    walls = room_walls(rects)
    for si in range(int(rng.integers(0, 3))):
        if count[0] + 6 > n_total:
            break
        wi = int(rng.integers(len(walls)))
        a, b, nin = (np.asarray(x, float) for x in walls[wi])
        L = float(np.linalg.norm(b - a))
        w = min(rng.uniform(0.8, 2.0), L - 0.7)
        if w < 0.6:
            continue
        c = rng.uniform(0.3 + w / 2, L - 0.3 - w / 2)
        if any(o[0] == wi and o[1] < c + w / 2 and o[2] > c - w / 2 for o in openings):
            continue
        tdir = (b - a) / L
        dep = rng.uniform(0.25, 0.4)
        p = a + tdir * c + nin * (dep / 2 + 0.01)
        yaw = math.degrees(math.atan2(tdir[0], tdir[1])) - 90.0   # local x along the wall
        boards = int(rng.integers(3, 5))
        top = min(rng.uniform(1.4, 2.0), H - 0.3)
        mat = random_material(rng, kind=("diffuse", "roughplastic")[int(rng.integers(2))])
        for bi in range(boards):
            y = 0.1 + (top - 0.1) * bi / (boards - 1)
            add(f"shelf{si}_board{bi}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), mat,
                Transform((_f(p[0]), _f(y), _f(p[1])), (0.0, _f(yaw), 0.0), (_f(w / 2), 0.015, _f(dep / 2))),
                radius=w / 2 + 0.1, movable=False)
            if bi > 0 or boards == 1:
                supports.append((p[0], p[1], y + 0.015, w / 2 * 0.9, dep / 2 * 0.6, yaw))
        for side in (-1, 1):
            q = p + tdir * side * (w / 2 + 0.015)
            add(f"shelf{si}_side{'lr'[side > 0]}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), mat,
                Transform((_f(q[0]), _f((top + 0.1) / 2), _f(q[1])), (0.0, _f(yaw), 0.0),
                          (0.015, _f((top + 0.1) / 2 + 0.015), _f(dep / 2))),
                radius=top / 2 + 0.1, movable=False)
    # objects on supports and on the floor, nearly all in the first view
    vis_supports = [sp for sp in supports if in_view([sp[0], sp[2], sp[1]], max(sp[3], sp[4]))]
    for k in range(max(0, n_total - count[0])):
        on_support = bool(vis_supports) and rng.uniform() < 0.3
        must_see = rng.uniform() < 0.95
        pos = None
        for _ in range(30):
            if on_support:
                sx, sz, sy, hx, hz, yaw = vis_supports[int(rng.integers(len(vis_supports)))]
                size = math.exp(rng.uniform(math.log(0.05), math.log(0.18)))
                lx, lz = rng.uniform(-hx, hx), rng.uniform(-hz, hz)
                cy, sy_ = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
                x, z = sx + cy * lx + sy_ * lz, sz - sy_ * lx + cy * lz
                base_y = sy
            else:
                size = math.exp(rng.uniform(math.log(0.08), math.log(0.5)))
                base_y = 0.0
                if must_see:   # where a ray through a random image point meets the floor
                    px, py = rng.uniform(-1, 1, 2)
                    d = fw + rt * px * tan_x + up_ * py * tan_x
                    if d[1] >= -1e-3:
                        continue
                    hit = origin + d * (-origin[1] / d[1])
                    x, z = float(hit[0]), float(hit[2])
                    if not inside_plan(rects, np.array([[x, z]]), size + 0.05)[0]:
                        continue
                else:
                    x, z = _sample_in_plan(rng, rects, size + 0.05)
            if must_see and not in_view([x, base_y + size, z], size * 1.2):
                continue
            dist = math.dist((x, base_y + size, z), origin)
            size = min(size, 0.3 * dist * tan_x / 1.2)   # no object fills the view
            if dist < 1.2 * size + 0.3:
                continue
            pos = (x, z, base_y, size)
            break
        if pos is None:
            continue
        x, z, base_y, size = pos
        shape, half = random_shape(rng, user_models, cfg.p_user_model)
        scale, rot, rest, radius = upright(rng, half, size)
        floating = (not on_support) and rng.uniform() < cfg.p_floating
        y = base_y + rest + (rng.uniform(0.3, 1.2) if floating else 0.0)
        y = min(y, H - rest - 0.05)
        add(f"obj_{k:03d}", shape, random_material(rng), Transform((_f(x), _f(y), _f(z)), rot, scale),
            radius=radius, planar=not floating)

    # four area lights: emissive rectangles under the ceiling (plane faces +y: turned over) or on walls
    for li in range(4):
        col = light_color(rng)
        hx, hz = rng.uniform(0.15, 0.5), rng.uniform(0.15, 0.5)
        area = 4 * hx * hz
        L = col * _logu(rng, AREA_POWER) / area
        if rng.uniform() < 0.75:
            p = _sample_in_plan(rng, rects, max(hx, hz) + 0.1)
            t = Transform((_f(p[0]), _f(H - 0.01), _f(p[1])), (180.0, _f(rng.uniform(0, 90)), 0.0), (_f(hx), 1.0, _f(hz)))
        else:
            a, b, nin = (np.asarray(x, float) for x in walls[int(rng.integers(len(walls)))])
            Lw = float(np.linalg.norm(b - a))
            q = a + (b - a) * rng.uniform(0.2, 0.8) + nin * 0.01
            yaw = math.degrees(math.atan2(nin[0], nin[1]))
            t = Transform((_f(q[0]), _f(rng.uniform(1.4, H - 0.3 - hz)), _f(q[1])), (90.0, _f(yaw), 0.0),
                          (_f(min(hx, Lw / 3)), 1.0, _f(min(hz, 0.3))))
        objects.append(Placed(f"light_area_{li}", MeshSpec("plane", {"resolution": 1}),
                              diffuse((0.8, 0.8, 0.8)), t, radius=math.hypot(hx, hz), keep=True, movable=False,
                              budget=False, emitter=tuple(_f(c) for c in L)))
    # one point light, one environment probe seen through the openings
    p = _sample_in_plan(rng, rects, 0.4)
    lights = [LightSpec("point", {"position": [_f(p[0]), _f(rng.uniform(0.6, H - 0.3)), _f(p[1])],
                                  "intensity": [_f(c) for c in light_color(rng) * _logu(rng, POINT_INTENSITY)]}),
              LightSpec("envmap", {"probe": probe_params(rng, sky=_logu(rng, INDOOR_SKY), sun_irradiance=INDOOR_SUN),
                                   "scale": 1.0, "rotation": _f(rng.uniform(0, 360))})]
    return Layout(objects=objects, lights=lights, origin=origin, target=target,
                  camera_step=_f(rng.uniform(0.02, 0.08)), clamp=clamp)


def cams_make(origin, target, fov):
    from scene_gen.cameras import make_camera
    return make_camera(origin, target, fov)
