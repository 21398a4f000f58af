"""Procedural rooms: floor plans, openings and room meshes (numpy only).

A room is a union of axis-aligned rectangles in the x-z plane (metres, floor at y = 0, +y up) with a
ceiling at ``height``. Its walls are the boundary of that union, found on the grid of rectangle
edges and merged into straight runs, listed in a fixed order (:func:`room_walls`), so an opening is
``[wall_index, u0, u1, v0, v1]``: metres along the wall from its start and above the floor.

``room_geometry(params)`` (``MeshSpec(kind='room', params=...)``, built by ``scene_gen.meshes``) makes one part of the room,
``params['part']`` in ``floor | walls | ceiling``, with faces that look *into* the room (a camera
inside sees the front side), holes where the openings and ``skylights`` are, UVs in metres and flat
normals. Meshes are in world units and are not normalised.

Room types (:data:`ROOM_TYPES`, >= 8): box, long, L, T, U, cross, hall (with pillars), loft (skylights),
studio (one glazed wall). The indoor scene family (``scene_gen.families.indoor``) furnishes and lights them.
"""
from __future__ import annotations

import math

import numpy as np

from scene_gen.errors import MeshError, SpecError

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


def room_geometry(params: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One part of a room (``params``: ``rects``, ``height``, ``openings``, ``skylights``, ``part``) as
    (vertices float64 N×3, faces int32 M×3, normals float64 N×3, uv float64 N×2).

    Faces look into the room; vertices are in metres (not normalised); UVs are metres along the surface."""
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
    return v, f, n, uv


# ---------------------------------------------------------------------------------------------
# points in a plan

def sample_in_plan(rng: np.random.Generator, rects, margin: float, n_try: int = 4) -> np.ndarray:
    """A uniform random x-z point (float64, 2) inside the plan at least ``margin`` from every wall;
    the first rectangle's centre when ``n_try`` batches of 32 candidates all miss."""
    r = np.asarray(rects, np.float64)
    lo, hi = r[:, :2].min(0), r[:, 2:].max(0)
    for _ in range(n_try):   # batches of candidates; the first inside one wins
        p = rng.uniform(lo, hi, (32, 2))
        ok = np.flatnonzero(inside_plan(r, p, margin))
        if len(ok):
            return p[ok[0]]
    c = r[0]
    return np.array([(c[0] + c[2]) / 2, (c[1] + c[3]) / 2])


def clamp_into(rects, height: float, margin: float = 0.35):
    """A function mapping a point (x, y, z) to the nearest one inside the room: ``margin`` from the
    walls, 0.2 from the floor and the ceiling (camera paths in a room)."""
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
