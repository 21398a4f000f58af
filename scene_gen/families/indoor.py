"""Indoor scenes: a procedural room, furniture, ~50 meshes, four area lights, one point light and an
HDR probe seen through the openings (numpy only).

The room is one of :data:`scene_gen.rooms.ROOM_TYPES` with its windows, doors and skylights. The
camera stands near the boundary at standing or sitting height and looks across the room, low, along
the longest of a few clear sight lines. Tables and shelves against the walls give surfaces to put
things on; the meshes go on them and on the floor where random rays through the image meet it, so
nearly all are in the first view. The area lights are emissive rectangles under the ceiling or on
the walls.

Each step below draws from the random streams in turn: reordering the steps, or the draws inside
one, changes every indoor scene of every dataset (``tests/test_scene_gen_pinned.py`` holds some).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from scene_gen import cameras as cams
from scene_gen.families import Setting, register_family
from scene_gen.layout import Layout, Placed, light_color, probe_params, random_shape, upright
from scene_gen.materials import diffuse, random_color, random_material, random_texture
from scene_gen.rooms import (ROOM_TYPES, clamp_into, inside_plan, random_openings, random_plan, room_walls,
                             sample_in_plan)
from scene_gen.spec import LightSpec, MaterialSpec, MeshSpec, Transform

# Radiance scales chosen so a 64-spp preview with the fixed log tone map is well exposed.
AREA_POWER = (1.5, 6.0)       # radiance x area of each emissive rectangle (log-uniform)
POINT_INTENSITY = (1.0, 6.0)  # point light intensity (log-uniform)
INDOOR_SKY = (0.8, 2.5)       # probe sky radiance seen through the windows (log-uniform)
INDOOR_SUN = 8.0              # probe sun irradiance: sunlit patches through windows stand out

SETTINGS = {"indoor_objects": Setting(50, "int", 0, 10000, "meshes placed in a room (furniture included)"),
            "p_lamps": Setting(0.0, "probability", doc="one to three small, very bright lamps in view "
                                                        "(scene_gen.phenomena)", newer=True),
            "p_panels_in_view": Setting(0.0, "probability", doc="an emissive panel on a wall or the ceiling in view "
                                                                "(scene_gen.phenomena)", newer=True)}


def _f(x) -> float:
    return round(float(x), 4)     # as scene_gen.rooms rounds plans


def _logu(rng, lo_hi) -> float:
    return math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1])))


@dataclass
class Room:
    """A room's plan (``rects``, ``height``, ``pillars``), its openings and its walls (``room_walls``)."""
    type: str
    rects: list
    height: float
    pillars: list
    openings: list
    skylights: list
    walls: list


@dataclass
class View:
    """The first camera: what it sees (``sees(point, radius)``) and its basis."""
    origin: np.ndarray
    sees: Callable               # sees(point, radius) -> bool (scene_gen.cameras.frustum_test)
    tan_x: float
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray

    def floor_hit(self, rng: np.random.Generator) -> np.ndarray | None:
        """Where a ray through a random image point meets the floor (None: it points up)."""
        px, py = rng.uniform(-1, 1, 2)
        d = self.forward + self.right * px * self.tan_x + self.up * py * self.tan_x
        if d[1] >= -1e-3:
            return None
        return self.origin + d * (-self.origin[1] / d[1])


@register_family("indoor", seed_index=0, settings=SETTINGS)
def layout_indoor(rng: np.random.Generator, r_cam: np.random.Generator, cfg, fov: float, res: int,
                  user_models: list[str]) -> Layout:
    """Room, furniture, ~``cfg.indoor_objects`` meshes, 4 area lights, 1 point light, 1 probe (a ``scene_gen.layout.Layout``)."""
    room = random_room(rng)
    structure = room_surfaces(rng, room)
    origin, target = camera_across(r_cam, room)
    view = first_view(origin, target, fov, res)
    tables, table_tops = place_tables(rng, room, view, cfg.indoor_objects)
    shelves, boards = place_shelves(rng, room, cfg.indoor_objects - len(tables))
    n = max(0, cfg.indoor_objects - len(tables) - len(shelves))
    content = place_content(rng, room, view, table_tops + boards, n, cfg, user_models)
    panels = area_lights(rng, room)
    lights = point_light_and_probe(rng, room)
    return Layout(objects=structure + tables + shelves + content + panels, lights=lights, origin=origin,
                  target=target, camera_step=_f(rng.uniform(0.02, 0.08)), clamp=clamp_into(room.rects, room.height))


def random_room(rng: np.random.Generator) -> Room:
    """A room type, its plan and its openings."""
    room_type = ROOM_TYPES[int(rng.integers(len(ROOM_TYPES)))]
    plan = random_plan(rng, room_type)
    rects, H = plan["rects"], plan["height"]
    openings, skylights = random_openings(rng, room_type, rects, H)
    return Room(room_type, rects, H, plan["pillars"], openings, skylights, room_walls(rects))


def room_surfaces(rng: np.random.Generator, room: Room) -> list[Placed]:
    """Floor, walls and ceiling (one mesh each, with their materials) and the pillars."""
    H = room.height
    base = {"rects": room.rects, "height": H, "openings": room.openings, "skylights": room.skylights,
            "type": room.type}
    ftex = random_texture(rng, kind=("checker", "stripes", "noise", "cells")[int(rng.integers(4))])
    floor_mat = (MaterialSpec("roughplastic", base_color=ftex.color0, specular_color=(0.04, 0.04, 0.04),
                              roughness=0.4, params={"int_ior": 1.5}, texture=ftex)
                 if rng.uniform() < 0.5 else diffuse(ftex.color0, texture=ftex))
    wall_c = random_color(rng, v_range=(0.65, 0.95), s_max=0.35)
    wall_mat = diffuse(wall_c, texture=random_texture(rng, wall_c, kind="stripes") if rng.uniform() < 0.25 else None)
    ceil_mat = diffuse(random_color(rng, v_range=(0.8, 0.95), s_max=0.1))
    out = [Placed(f"room_{part}", MeshSpec("room", {**base, "part": part}), mat, Transform(),
                  radius=1e3, keep=True, movable=False, budget=False)
           for part, mat in (("floor", floor_mat), ("walls", wall_mat), ("ceiling", ceil_mat))]
    for i, (x, z, s) in enumerate(room.pillars):
        out.append(Placed(f"pillar_{i}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), wall_mat,
                          Transform((x, _f(H / 2), z), (0, 0, 0), (_f(s), _f(H / 2), _f(s))),
                          radius=math.hypot(s * 1.5, H / 2), movable=False))
    return out


def camera_across(r_cam: np.random.Generator, room: Room) -> tuple[np.ndarray, np.ndarray]:
    """Camera origin and target: near the boundary, looking across the room with a clear line of
    sight (the longest of a few clear sight lines), the target low so the floor near it is in view."""
    rects, H = room.rects, room.height
    origin = target = None
    best = -1.0
    for _ in range(200):
        o = sample_in_plan(r_cam, rects, 0.4)
        t = sample_in_plan(r_cam, rects, 0.3)
        dist = float(np.linalg.norm(t - o))
        if dist < 2.2 or dist <= best:
            continue
        line = o[None] + np.linspace(0, 1, 24)[:, None] * (t - o)[None]
        if not inside_plan(rects, line, 0.1).all():
            continue
        best = dist
        # the eye at standing or sitting height
        origin = np.array([o[0], r_cam.uniform(1.1, min(1.9, H - 0.4)), o[1]])
        target = np.array([t[0], r_cam.uniform(0.1, 0.7), t[1]])
        if best > 4.0:
            break
    if origin is None:  # pragma: no cover - every plan has a 2.2 m line of sight
        origin, target = np.array([0.0, 1.5, 0.0]), np.array([1.0, 0.8, 1.0])
    return origin, target


def first_view(origin: np.ndarray, target: np.ndarray, fov: float, res: int) -> View:
    cam0 = cams.make_camera(origin, target, fov)
    rt, up_, fw = cams.basis(cam0)
    return View(origin, cams.frustum_test(cam0, (res, res)), math.tan(math.radians(fov) / 2), rt, up_, fw)


def place_tables(rng: np.random.Generator, room: Room, view: View, budget: int) -> tuple[list[Placed], list]:
    """Up to two tables (top, leg, foot; 3 objects each within ``budget``), mostly in view, and their
    tops as supports ``(x, z, y_top, half_x, half_z, yaw)``."""
    out, supports = [], []
    wood = random_material(rng, kind=("diffuse", "roughplastic", "principled")[int(rng.integers(3))])
    for ti in range(int(rng.integers(0, 3))):
        if len(out) + 3 > budget:
            break
        hx, hz, ht = rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.5), rng.uniform(0.68, 0.78)
        for _ in range(30):
            p = sample_in_plan(rng, room.rects, max(hx, hz) + 0.3)
            if view.sees([p[0], ht / 2, p[1]], max(hx, hz)) or rng.uniform() < 0.1:
                break
        yaw = rng.uniform(0, 360)
        out += [
            Placed(f"table{ti}_top", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), wood,
                   Transform((_f(p[0]), _f(ht - 0.02), _f(p[1])), (0.0, _f(yaw), 0.0), (_f(hx), 0.02, _f(hz))),
                   radius=math.hypot(hx, hz), movable=False),
            Placed(f"table{ti}_leg", MeshSpec("cylinder", {"radius": 1.0, "height": 2.0, "sections": 24}), wood,
                   Transform((_f(p[0]), _f((ht - 0.04) / 2), _f(p[1])), (0.0, 0.0, 0.0),
                             (0.06, _f((ht - 0.04) / 2), 0.06)),
                   radius=ht / 2, movable=False),
            Placed(f"table{ti}_foot", MeshSpec("cylinder", {"radius": 1.0, "height": 2.0, "sections": 24}), wood,
                   Transform((_f(p[0]), 0.02, _f(p[1])), (0.0, 0.0, 0.0),
                             (_f(min(hx, hz) * 0.7), 0.02, _f(min(hx, hz) * 0.7))),
                   radius=min(hx, hz), movable=False)]
        supports.append((p[0], p[1], ht, hx * 0.85, hz * 0.85, yaw))
    return out, supports


def place_shelves(rng: np.random.Generator, room: Room, budget: int) -> tuple[list[Placed], list]:
    """Up to two shelves against walls, clear of the openings (boards and sides, at most ``budget``
    objects in all), and their boards above the lowest as supports."""
    out, supports = [], []
    walls, H = room.walls, room.height
    for si in range(int(rng.integers(0, 3))):
        if len(out) + 6 > budget:
            break
        wi = int(rng.integers(len(walls)))
        a, b, nin = (np.asarray(x, float) for x in walls[wi])
        L = float(np.linalg.norm(b - a))
        w = min(rng.uniform(0.8, 2.0), L - 0.7)
        if w < 0.6:
            continue
        c = rng.uniform(0.3 + w / 2, L - 0.3 - w / 2)
        if any(o[0] == wi and o[1] < c + w / 2 and o[2] > c - w / 2 for o in room.openings):
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
            out.append(Placed(f"shelf{si}_board{bi}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), mat,
                              Transform((_f(p[0]), _f(y), _f(p[1])), (0.0, _f(yaw), 0.0), (_f(w / 2), 0.015, _f(dep / 2))),
                              radius=w / 2 + 0.1, movable=False))
            if bi > 0 or boards == 1:
                supports.append((p[0], p[1], y + 0.015, w / 2 * 0.9, dep / 2 * 0.6, yaw))
        for side in (-1, 1):
            q = p + tdir * side * (w / 2 + 0.015)
            out.append(Placed(f"shelf{si}_side{'lr'[side > 0]}", MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), mat,
                              Transform((_f(q[0]), _f((top + 0.1) / 2), _f(q[1])), (0.0, _f(yaw), 0.0),
                                        (0.015, _f((top + 0.1) / 2 + 0.015), _f(dep / 2))),
                              radius=top / 2 + 0.1, movable=False))
    return out, supports


def place_content(rng: np.random.Generator, room: Room, view: View, supports: list, n: int, cfg,
                  user_models: list[str]) -> list[Placed]:
    """``n`` random meshes (fewer where no spot is found) on the supports in view and on the floor,
    nearly all in the first view, a few floating."""
    out = []
    vis_supports = [sp for sp in supports if view.sees([sp[0], sp[2], sp[1]], max(sp[3], sp[4]))]
    for k in range(n):
        on_support = bool(vis_supports) and rng.uniform() < 0.3
        must_see = rng.uniform() < 0.95
        pos = _content_spot(rng, room, view, vis_supports, on_support, must_see)
        if pos is None:
            continue
        x, z, base_y, size = pos
        shape, half = random_shape(rng, user_models, cfg.p_user_model)
        scale, rot, rest, radius = upright(rng, half, size)
        floating = (not on_support) and rng.uniform() < cfg.p_floating
        y = base_y + rest + (rng.uniform(0.3, 1.2) if floating else 0.0)
        y = min(y, room.height - rest - 0.05)
        out.append(Placed(f"obj_{k:03d}", shape, random_material(rng), Transform((_f(x), _f(y), _f(z)), rot, scale),
                          radius=radius, planar=not floating))
    return out


def _content_spot(rng, room: Room, view: View, vis_supports: list, on_support: bool, must_see: bool):
    """(x, z, base height, size) of one content mesh, or None when 30 tries find no place."""
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
            if must_see:
                hit = view.floor_hit(rng)
                if hit is None:
                    continue
                x, z = float(hit[0]), float(hit[2])
                if not inside_plan(room.rects, np.array([[x, z]]), size + 0.05)[0]:
                    continue
            else:
                x, z = sample_in_plan(rng, room.rects, size + 0.05)
        if must_see and not view.sees([x, base_y + size, z], size * 1.2):
            continue
        dist = math.dist((x, base_y + size, z), view.origin)
        size = min(size, 0.3 * dist * view.tan_x / 1.2)   # no object fills the view
        if dist < 1.2 * size + 0.3:
            continue
        return x, z, base_y, size
    return None


def area_lights(rng: np.random.Generator, room: Room) -> list[Placed]:
    """Four emissive rectangles: under the ceiling (a plane faces +y: turned over) or on a wall."""
    out = []
    H = room.height
    for li in range(4):
        col = light_color(rng)
        hx, hz = rng.uniform(0.15, 0.5), rng.uniform(0.15, 0.5)
        area = 4 * hx * hz
        L = col * _logu(rng, AREA_POWER) / area
        if rng.uniform() < 0.75:
            p = sample_in_plan(rng, room.rects, max(hx, hz) + 0.1)
            t = Transform((_f(p[0]), _f(H - 0.01), _f(p[1])), (180.0, _f(rng.uniform(0, 90)), 0.0), (_f(hx), 1.0, _f(hz)))
        else:
            a, b, nin = (np.asarray(x, float) for x in room.walls[int(rng.integers(len(room.walls)))])
            Lw = float(np.linalg.norm(b - a))
            q = a + (b - a) * rng.uniform(0.2, 0.8) + nin * 0.01
            yaw = math.degrees(math.atan2(nin[0], nin[1]))
            t = Transform((_f(q[0]), _f(rng.uniform(1.4, H - 0.3 - hz)), _f(q[1])), (90.0, _f(yaw), 0.0),
                          (_f(min(hx, Lw / 3)), 1.0, _f(min(hz, 0.3))))
        out.append(Placed(f"light_area_{li}", MeshSpec("plane", {"resolution": 1}),
                          diffuse((0.8, 0.8, 0.8)), t, radius=math.hypot(hx, hz), keep=True, movable=False,
                          budget=False, emitter=tuple(_f(c) for c in L)))
    return out


def point_light_and_probe(rng: np.random.Generator, room: Room) -> list[LightSpec]:
    """One point light in the room and one environment probe seen through the openings."""
    H = room.height
    p = sample_in_plan(rng, room.rects, 0.4)
    return [LightSpec("point", {"position": [_f(p[0]), _f(rng.uniform(0.6, H - 0.3)), _f(p[1])],
                                "intensity": [_f(c) for c in light_color(rng) * _logu(rng, POINT_INTENSITY)]}),
            LightSpec("envmap", {"probe": probe_params(rng, sky=_logu(rng, INDOOR_SKY), sun_irradiance=INDOOR_SUN),
                                 "scale": 1.0, "rotation": _f(rng.uniform(0, 360))})]
