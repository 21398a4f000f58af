"""A camera's matrices and projections, in one place (numpy only): the look-at frame the Mitsuba sensor is
built from (``scene_gen.to_mitsuba``), and the projections the renderer's features and guides use.

Conventions (Mitsuba's):

- Camera space: +z forward (view axis), +y up, +x *left*. ``camera_to_world`` is the look-at matrix.
- ``fov`` is the full horizontal field of view in degrees; pixels are square, so
  ``tan_half_y = tan_half_x * H / W``.
- Pixel coordinates ``(px, py)`` (float): ``px`` in [0, W) left to right, ``py`` in [0, H) top to
  bottom; pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)`` and its centre is ``(i + 0.5, j + 0.5)``.
- Clip space (``world_to_clip = projection @ view``): OpenGL-like, ``ndc = clip[:3] / clip[3]`` with
  ``ndc_x = 2 px / W - 1`` (right), ``ndc_y = 1 - 2 py / H`` (up) and ``ndc_z`` in [-1, 1] from
  ``near`` to ``far``; ``clip_w`` is the camera-space depth ``z``.

Thin lens (Mitsuba ``thinlens``): the aperture is a disk of radius ``A`` at the camera origin in the
z = 0 plane and the plane of focus is ``z = F`` (``focus_distance``). A point at camera depth ``z``
is imaged as a disk on the focus plane of radius ``A |z - F| / z``; in pixels that is the signed
circle of confusion :func:`coc_pixels` (radius, + behind the focus plane, - in front of it). For a
sample through lens position ``l`` (unit disk, camera-space x/y axes, i.e. ``l_x`` points left),
its film position and the pinhole projection of its hit point differ by exactly
``film_px - pinhole_px = -coc * (l_x, l_y)`` (px grows to the right = -x, py grows down = -y).
"""
from __future__ import annotations

import math

import numpy as np

from scene_gen.spec import CameraSpec

NEAR = 1e-2   # the sensor's clip planes (world units); Mitsuba starts camera rays on the near plane
FAR = 1e4


def camera_to_world(cam: CameraSpec) -> np.ndarray:
    """4x4 camera-to-world (float64) with Mitsuba's look-at convention (+z forward, +y up, +x left)."""
    o, t, up = (np.asarray(x, np.float64) for x in (cam.origin, cam.target, cam.up))
    d = t - o
    d /= np.linalg.norm(d)
    left = np.cross(up, d)
    if np.linalg.norm(left) < 1e-9:  # up parallel to the view direction: pick another up
        left = np.cross(np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 0.0, 1.0]), d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def tan_half_fov_x(cam: CameraSpec) -> float:
    return math.tan(math.radians(cam.fov) / 2.0)


def projection(cam: CameraSpec, res: tuple[int, int], near: float = NEAR, far: float = FAR) -> np.ndarray:
    """4x4 camera-to-clip matrix (float64) for the conventions of this module; ``res = (W, H)``."""
    w, h = res
    t = tan_half_fov_x(cam)
    aspect = w / h
    p = np.zeros((4, 4))
    p[0, 0] = -1.0 / t                     # camera +x is left, ndc +x is right
    p[1, 1] = aspect / t
    p[2, 2] = (far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = 1.0
    return p


def world_to_clip(cam: CameraSpec, res: tuple[int, int]) -> np.ndarray:
    """4x4 world-to-clip (float64) = projection @ inverse(camera_to_world)."""
    return projection(cam, res) @ np.linalg.inv(camera_to_world(cam))


def project_pixels(world_to_clip_m: np.ndarray, pts: np.ndarray, res: tuple[int, int], w: np.ndarray | float = 1.0
                   ) -> np.ndarray:
    """Pixel coordinates (float64, N×2) of world points (N×3; ``w = 0`` rows: directions at infinity).

    Points behind the camera, or in front of it but nearer than the near plane (which the camera
    clips: no pixel saw them, and their projection grows without bound), get NaN (callers decide what
    to do with them).
    """
    W, H = res
    pts = np.asarray(pts, np.float64)
    w = np.broadcast_to(np.asarray(w, np.float64), pts.shape[:-1])
    m = np.asarray(world_to_clip_m, np.float64)
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    # row by row instead of a matmul: no BLAS thread pool for an N×4 @ 4×4 product
    cx, cy, cw = (m[i, 0] * x + m[i, 1] * y + m[i, 2] * z + m[i, 3] * w for i in (0, 1, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = cw > np.where(w > 0, NEAR, 1e-12)
        nx = np.where(ok, cx / np.where(ok, cw, 1.0), np.nan)
        ny = np.where(ok, cy / np.where(ok, cw, 1.0), np.nan)
    return np.stack([(nx + 1.0) * 0.5 * W, (1.0 - ny) * 0.5 * H], axis=-1)


def coc_pixels(cam: CameraSpec, z: np.ndarray, width: int) -> np.ndarray:
    """Signed circle-of-confusion radius in pixels (float64) for camera depths ``z`` (> 0, may be inf).

    ``A (z - F) / z`` on the focus plane, divided by the focus plane's pixel size
    ``2 F tan(fov_x / 2) / W``: 0 at ``z = F``, positive behind focus, negative in front; 0 for a pinhole.
    """
    z = np.asarray(z, np.float64)
    if not cam.defocus:
        return np.zeros_like(z)
    a, f = cam.aperture_radius, cam.focus_distance
    with np.errstate(divide="ignore", invalid="ignore"):
        c = a * (1.0 - f / z) * width / (2.0 * f * tan_half_fov_x(cam))   # z = inf: the limit a W / (2 F tan)
    return np.where(z > 0, c, 0.0)
