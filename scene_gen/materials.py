"""Random materials over Mitsuba's BSDF set, with procedural textures and random UV scale (numpy only).

``random_material(rng)`` draws a :class:`MaterialSpec` of one of ``spec.MATERIAL_KINDS``:

=================  =====================================================================
kind               params
=================  =====================================================================
diffuse            (base_color or texture)
conductor          ``material: "none"`` (a perfect conductor tinted by specular_color: a metal's F0)
roughconductor     ``material: "none"``, ``metal`` (name of the F0 colour used)
dielectric         ``int_ior``
roughdielectric    ``int_ior``
thindielectric     ``int_ior``
plastic            ``int_ior`` (base_color or texture under a smooth coat)
roughplastic       ``int_ior``
principled         ``metallic``, ``specular``, ``roughness``, ``clearcoat``, ``sheen``, ``anisotropic``
blend              ``weight`` and two ``children`` (non-blend materials)
=================  =====================================================================

``roughness`` (the per-sample feature) is perceptual, as ``scene_gen.to_mitsuba`` reads it: microfacet
``alpha = roughness ** 2`` (0 for smooth interfaces, 1 for diffuse); ``specular_color`` is the
normal-incidence reflectance (F0), used both for rendering conductors and as the specular-colour feature.
"""
from __future__ import annotations

import colorsys

import numpy as np

from scene_gen.errors import SpecError
from scene_gen.spec import MATERIAL_KINDS, PROCEDURAL_TEXTURE_KINDS, MaterialSpec, TextureSpec

# Relative frequency of each kind (sums need not be 1). Diffuse-ish surfaces dominate real scenes.
KIND_WEIGHTS = {
    "diffuse": 3.0, "conductor": 1.0, "roughconductor": 1.5, "dielectric": 1.0, "roughdielectric": 0.7,
    "thindielectric": 0.5, "plastic": 1.2, "roughplastic": 2.0, "principled": 2.0, "blend": 1.0,
}
# Normal-incidence reflectance (linear sRGB, approximate) of Mitsuba's named conductors.
METALS = {
    "Au": (1.0, 0.78, 0.34), "Ag": (0.97, 0.96, 0.91), "Cu": (0.96, 0.64, 0.54), "Al": (0.91, 0.92, 0.92),
    "Cr": (0.55, 0.56, 0.55), "W": (0.50, 0.49, 0.46), "none": (1.0, 1.0, 1.0),
}
TEXTURED_KINDS = ("diffuse", "plastic", "roughplastic", "principled")


def _f(x) -> float:
    """A plain Python float rounded to 6 decimals (short, exact JSON)."""
    return round(float(x), 6)


def random_color(rng: np.random.Generator, *, v_range=(0.05, 0.85), s_max: float = 0.9) -> tuple:
    """A linear-RGB albedo (float, 3) from HSV: hue uniform, saturation skewed low, value in ``v_range``."""
    h = rng.uniform()
    s = s_max * rng.uniform() ** 1.5
    v = rng.uniform(*v_range)
    r, g, b = colorsys.hsv_to_rgb(h, s, v)
    return tuple(_f(min(max(c, 0.0) ** 2.2, 1.0)) for c in (r, g, b))


def random_texture(rng: np.random.Generator, base: tuple | None = None, kind: str | None = None) -> TextureSpec:
    """A procedural texture (one of ``PROCEDURAL_TEXTURE_KINDS``) mixing two colours, UV scale log-uniform in
    [0.5, 16]."""
    kind = kind or PROCEDURAL_TEXTURE_KINDS[int(rng.integers(len(PROCEDURAL_TEXTURE_KINDS)))]
    c0 = base if base is not None else random_color(rng)
    c1 = random_color(rng) if rng.uniform() < 0.6 else tuple(_f(c * rng.uniform(0.2, 0.6)) for c in c0)
    return TextureSpec(kind=kind, color0=c0, color1=c1, uv_scale=_f(np.exp(rng.uniform(np.log(0.5), np.log(16.0)))),
                       seed=int(rng.integers(0, 2**31 - 1)))


def _rough(rng, hi: float = 0.75) -> float:
    """Perceptual roughness (alpha = r**2), log-uniform in [0.12, hi]."""
    return _f(np.exp(rng.uniform(np.log(0.12), np.log(hi))))


def random_material(rng: np.random.Generator, kind: str | None = None, *, allow_blend: bool = True,
                    p_texture: float = 0.5) -> MaterialSpec:
    """Draw one material; ``kind`` forces the BSDF kind (one of ``MATERIAL_KINDS``)."""
    if kind is None:
        kinds = [k for k in MATERIAL_KINDS if allow_blend or k != "blend"]
        w = np.array([KIND_WEIGHTS[k] for k in kinds])
        kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
    if kind not in MATERIAL_KINDS:
        raise SpecError(f"material kind must be one of {MATERIAL_KINDS}, got {kind!r}")
    base = random_color(rng)
    texture = random_texture(rng, base) if kind in TEXTURED_KINDS and rng.uniform() < p_texture else None
    zero = (0.0, 0.0, 0.0)
    if kind == "diffuse":
        return MaterialSpec(kind, base_color=base, specular_color=zero, roughness=1.0, texture=texture)
    if kind in ("conductor", "roughconductor"):
        names = sorted(METALS)
        metal = names[int(rng.integers(len(names)))]
        f0 = METALS[metal] if metal != "none" else random_color(rng, v_range=(0.6, 0.95), s_max=0.5)
        r = 0.0 if kind == "conductor" else _rough(rng)
        return MaterialSpec(kind, base_color=zero, specular_color=tuple(_f(c) for c in f0), roughness=r,
                            params={"material": "none", "metal": metal})
    if kind in ("dielectric", "roughdielectric", "thindielectric"):
        ior = _f(rng.uniform(1.3, 1.8))
        f0 = _f(((ior - 1) / (ior + 1)) ** 2)
        r = _rough(rng, 0.5) if kind == "roughdielectric" else 0.0
        return MaterialSpec(kind, base_color=zero, specular_color=(f0, f0, f0), roughness=r, params={"int_ior": ior})
    if kind in ("plastic", "roughplastic"):
        ior = _f(rng.uniform(1.4, 1.7))
        f0 = _f(((ior - 1) / (ior + 1)) ** 2)
        r = 0.0 if kind == "plastic" else _rough(rng)
        return MaterialSpec(kind, base_color=base, specular_color=(f0, f0, f0), roughness=r,
                            params={"int_ior": ior}, texture=texture)
    if kind == "principled":
        metallic = _f(rng.uniform() if rng.uniform() < 0.3 else 0.0)
        r = _f(rng.uniform(0.1, 0.9))
        specular = _f(rng.uniform(0.2, 0.8))
        f0d = 0.08 * specular
        spec = tuple(_f(f0d * (1 - metallic) + c * metallic) for c in base)
        params = {"metallic": metallic, "specular": specular,
                  "clearcoat": _f(rng.uniform() if rng.uniform() < 0.25 else 0.0),
                  "sheen": _f(rng.uniform() if rng.uniform() < 0.2 else 0.0),
                  "anisotropic": _f(rng.uniform(0, 0.8) if rng.uniform() < 0.2 else 0.0)}
        return MaterialSpec(kind, base_color=base, specular_color=spec, roughness=r, params=params, texture=texture)
    # blend of two non-blend materials (Mitsuba's blendbsdf: weight 0 -> first, 1 -> second)
    a = random_material(rng, allow_blend=False, p_texture=p_texture)
    b = random_material(rng, allow_blend=False, p_texture=p_texture)
    w = _f(rng.uniform(0.2, 0.8))
    mix = lambda x, y: tuple(_f((1 - w) * p + w * q) for p, q in zip(x, y))  # noqa: E731
    return MaterialSpec("blend", base_color=mix(a.base_color, b.base_color),
                        specular_color=mix(a.specular_color, b.specular_color),
                        roughness=_f((1 - w) * a.roughness + w * b.roughness), params={"weight": w}, children=(a, b))


def diffuse(color, texture: TextureSpec | None = None) -> MaterialSpec:
    """A plain diffuse material (room walls, backdrops)."""
    return MaterialSpec("diffuse", base_color=tuple(_f(c) for c in color), specular_color=(0.0, 0.0, 0.0),
                        roughness=1.0, texture=texture)
