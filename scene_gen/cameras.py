"""Cameras, projection, frustum tests and motion for random scenes (numpy only).

Conventions follow Mitsuba's ``look_at`` perspective/thin-lens sensors: ``fov`` is the horizontal
field of view in degrees (``fov_axis='x'``), ``y`` is up, units are metres. A camera path for a clip is
a centripetal-free (uniform) Catmull-Rom spline through random keys, sampled at one point per frame.
"""
from __future__ import annotations

import math

import numpy as np

from scene_gen.spec import CameraSpec


def _f(x) -> float:
    return round(float(x), 6)


def _vec(v) -> tuple:
    return tuple(_f(x) for x in v)


def basis(cam: CameraSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (right, up, forward) of a camera (float64, 3 each)."""
    o = np.asarray(cam.origin, float)
    fwd = np.asarray(cam.target, float) - o
    fwd /= np.linalg.norm(fwd)
    up = np.asarray(cam.up, float)
    right = np.cross(up, fwd)
    n = np.linalg.norm(right)
    if n < 1e-9:  # looking straight along up: pick any right
        right = np.cross([1.0, 0.0, 0.0] if abs(fwd[0]) < 0.9 else [0.0, 0.0, 1.0], fwd)
        n = np.linalg.norm(right)
    right /= n
    return right, np.cross(fwd, right), fwd


def tan_half(cam: CameraSpec, res: tuple[int, int]) -> tuple[float, float]:
    """tan of the half field of view along x and y for an image of ``res = (W, H)`` pixels."""
    tx = math.tan(math.radians(cam.fov) / 2)
    return tx, tx * res[1] / res[0]


def to_camera(cam: CameraSpec, points: np.ndarray) -> np.ndarray:
    """World points (float, N×3) → camera coordinates (x right, y up, z forward) (float64, N×3)."""
    r, u, f = basis(cam)
    d = np.atleast_2d(np.asarray(points, float)) - np.asarray(cam.origin, float)
    return np.stack([d @ r, d @ u, d @ f], axis=-1)


def sphere_in_frustum(cam: CameraSpec, centers: np.ndarray, radii: np.ndarray,
                      res: tuple[int, int]) -> np.ndarray:
    """Whether each bounding sphere (centres N×3, radii N) touches the view frustum (bool, N).

    Conservative test against the four side planes and the camera plane (no far plane)."""
    p = to_camera(cam, centers)
    radii = np.asarray(radii, float)
    tx, ty = tan_half(cam, res)
    inside = p[:, 2] > -radii
    for t, c in ((tx, 0), (ty, 1)):
        k = 1.0 / math.sqrt(1.0 + t * t)
        inside &= (p[:, c] - p[:, 2] * t) * k < radii
        inside &= (-p[:, c] - p[:, 2] * t) * k < radii
    return inside


def frustum_test(cam: CameraSpec, res: tuple[int, int]):
    """A fast scalar version of :func:`sphere_in_frustum` for one camera: ``f(center (3), radius) -> bool``."""
    r, u, fw = basis(cam)
    o = np.asarray(cam.origin, float)
    tx, ty = tan_half(cam, res)
    kx, ky = 1.0 / math.sqrt(1 + tx * tx), 1.0 / math.sqrt(1 + ty * ty)
    r, u, fw, o = r.tolist(), u.tolist(), fw.tolist(), o.tolist()

    def test(c, radius: float) -> bool:
        d = (c[0] - o[0], c[1] - o[1], c[2] - o[2])
        x = d[0] * r[0] + d[1] * r[1] + d[2] * r[2]
        y = d[0] * u[0] + d[1] * u[1] + d[2] * u[2]
        z = d[0] * fw[0] + d[1] * fw[1] + d[2] * fw[2]
        return (z > -radius and (x - z * tx) * kx < radius and (-x - z * tx) * kx < radius
                and (y - z * ty) * ky < radius and (-y - z * ty) * ky < radius)
    return test


def projected_radius_px(cam: CameraSpec, centers: np.ndarray, radii: np.ndarray, res: tuple[int, int]) -> np.ndarray:
    """Radius in pixels of each bounding sphere's projection (float64, N); huge when the camera is inside."""
    p = to_camera(cam, centers)
    dist = np.linalg.norm(p, axis=-1)
    radii = np.asarray(radii, float)
    focal_px = res[0] / 2 / math.tan(math.radians(cam.fov) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(radii / np.maximum(dist, 1e-9), 0.0, 0.999)
        r_px = focal_px * s / np.sqrt(1 - s * s)
    return np.where(dist <= radii, 1e9, r_px)


def swept_spheres(centers: np.ndarray, radii: np.ndarray, velocities: np.ndarray | None,
                  t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres of linear motion over ``tau in [t0, t1]``: centre at mid-time, radius grown by half the sweep."""
    centers = np.asarray(centers, float)
    radii = np.asarray(radii, float)
    if velocities is None:
        return centers, radii
    v = np.asarray(velocities, float)
    mid = centers + v * (0.5 * (t0 + t1))
    return mid, radii + np.linalg.norm(v, axis=-1) * 0.5 * (t1 - t0)


def visible_any_frame(cameras, centers, radii, velocities, res, shutter: float) -> np.ndarray:
    """Whether each object (with its motion sweep during each frame's exposure) is in some frame's frustum (bool, N)."""
    vis = np.zeros(len(radii), bool)
    for f, cam in enumerate(cameras):
        # Split each exposure into a few pieces so long sweeps stay tight.
        for a in np.linspace(f, f + shutter, 4)[:-1]:
            b = a + shutter / 3
            c, r = swept_spheres(centers, radii, velocities, a, b if shutter > 0 else a)
            vis |= sphere_in_frustum(cam, c, r, res)
    return vis


def max_projected_radius(cameras, centers, radii, velocities, res) -> np.ndarray:
    """The largest projected radius in pixels of each object over all frames (float64, N)."""
    out = np.zeros(len(radii))
    for f, cam in enumerate(cameras):
        c = np.asarray(centers, float) if velocities is None else np.asarray(centers, float) + np.asarray(velocities) * f
        out = np.maximum(out, projected_radius_px(cam, c, radii, res))
    return out


def sample_fov(rng: np.random.Generator, fov_range: tuple[float, float]) -> float:
    """Field of view in degrees, uniform in ``fov_range`` (sbmc: 15–65°)."""
    return _f(rng.uniform(*fov_range))


def sample_aperture(rng: np.random.Generator, focus_distance: float, aperture_range: tuple[float, float]) -> float:
    """Lens radius: log-uniform fraction (``aperture_range``) of the focus distance."""
    lo, hi = aperture_range
    return _f(focus_distance * math.exp(rng.uniform(math.log(lo), math.log(hi))))


def catmull_rom(keys: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Uniform Catmull-Rom spline through ``keys`` (K×D, K >= 2) at ``t`` in [0, 1] (float64, T×D)."""
    keys = np.asarray(keys, float)
    k = len(keys)
    pts = np.concatenate([2 * keys[:1] - keys[1:2], keys, 2 * keys[-1:] - keys[-2:-1]])
    s = np.clip(np.asarray(t, float), 0.0, 1.0) * (k - 1)
    i = np.minimum(np.floor(s).astype(int), k - 2)
    u = (s - i)[:, None]
    p0, p1, p2, p3 = pts[i], pts[i + 1], pts[i + 2], pts[i + 3]
    return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3)


def camera_path(rng: np.random.Generator, origin, target, num_frames: int, *, step: float,
                clamp=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """A smooth path of (origin, target) pairs, one per frame, starting at the given camera.

    Keys are spaced about ``step * 8`` frames apart (world units per frame ~ ``step``); ``clamp`` maps
    points back into the allowed region (e.g. inside the room)."""
    origin = np.asarray(origin, float)
    target = np.asarray(target, float)
    if num_frames <= 1:
        return [(origin, target)]
    n_keys = 2 + (num_frames - 1) // 12
    seg = step * (num_frames - 1) / (n_keys - 1)
    o_keys, t_keys = [origin], [target]
    heading = rng.normal(size=3)
    heading[1] *= 0.2
    heading /= np.linalg.norm(heading)
    for _ in range(n_keys - 1):
        d = heading + 0.5 * rng.normal(size=3) * np.array([1.0, 0.2, 1.0])
        d /= np.linalg.norm(d)
        o = o_keys[-1] + d * seg
        tg = t_keys[-1] + rng.normal(size=3) * np.array([1.0, 0.3, 1.0]) * seg * 0.5
        if clamp is not None:
            o, tg = clamp(o), clamp(tg)
        o_keys.append(o)
        t_keys.append(tg)
    t = np.linspace(0.0, 1.0, num_frames)
    os_, ts = catmull_rom(np.stack(o_keys), t), catmull_rom(np.stack(t_keys), t)
    if clamp is not None:
        os_ = np.stack([clamp(p) for p in os_])
        ts = np.stack([clamp(p) for p in ts])
    out = []
    for o, tg in zip(os_, ts):
        if np.linalg.norm(tg - o) < 0.5:  # keep a usable look-at distance
            tg = o + (tg - o + 1e-3) / max(np.linalg.norm(tg - o), 1e-3) * 0.5
        out.append((o, tg))
    return out


def make_camera(origin, target, fov: float, aperture_radius: float = 0.0, focus_distance: float = 1.0) -> CameraSpec:
    return CameraSpec(origin=_vec(origin), target=_vec(target), up=(0.0, 1.0, 0.0), fov=_f(fov),
                      aperture_radius=_f(aperture_radius), focus_distance=_f(max(focus_distance, 1e-3)))


def random_velocity(rng: np.random.Generator, radius: float, speed_range: tuple[float, float], *,
                    planar: bool = True) -> tuple:
    """A linear velocity (world units per frame): speed uniform in ``speed_range`` object radii per frame,
    horizontal when ``planar`` (objects slide on the ground), else any direction."""
    d = rng.normal(size=3)
    if planar:
        d[1] = 0.0
    d /= max(np.linalg.norm(d), 1e-9)
    return _vec(d * radius * rng.uniform(*speed_range))
