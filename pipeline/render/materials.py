"""The specular colour and roughness features of a loaded Mitsuba BSDF, asked of the BSDF itself.

The renderer learns materials from the scene it renders, never from a description of it, so a scene
the project generated and a user's scene file go through one door. :func:`bsdf_features` walks a BSDF
(its nested BSDFs through Mitsuba's traversal) and reads its parameters:

==================================  ==========================================  ==========================
BSDF (Mitsuba class)                specular colour (F0, linear RGB)             roughness (perceptual)
==================================  ==========================================  ==========================
diffuse                             0                                            1
conductor / roughconductor          ``specular_reflectance`` x F0 of (eta, k)    0 / sqrt(alpha)
dielectric / thin / roughdielectric ``((eta - 1) / (eta + 1))^2``                0 / 0 / sqrt(alpha)
plastic / roughplastic              ``((eta - 1) / (eta + 1))^2``                0 / sqrt(alpha)
principled                          ``F0 (1 - metallic) + base metallic``         ``roughness``
twosided                            its front BSDF's
blendbsdf                           ``(1 - weight) a + weight b`` for both
mask, bumpmap, normalmap            the nested BSDF's
==================================  ==========================================  ==========================

F0 of a conductor is ``((eta - 1)^2 + k^2) / ((eta + 1)^2 + k^2)`` per channel (Mitsuba's ``material``
``none`` is eta 0, k 1: a perfect mirror, F0 1). ``alpha`` is the microfacet roughness (anisotropic:
the mean of ``alpha_u`` and ``alpha_v``); the feature is its square root, the perceptual roughness the
generator draws (``scene_gen.materials``); a principled BSDF's F0 is ``0.08 specular``, or its ``eta``'s
where the file gives one. A textured parameter counts with its mean over the texture
(a bitmap's texels, a checkerboard's two colours, any other texture's values on a 16x16 grid of UVs).

**Fallback** for a BSDF none of the rows names (``measured``, ``hair``, a plugin of the user's): by its
lobes. Only diffuse lobes: specular 0, roughness 1. Only delta lobes: roughness 0. Otherwise roughness
``sqrt(alpha)`` where the BSDF exposes ``alpha``, else :data:`FALLBACK_ROUGHNESS`; specular colour its
``specular_reflectance`` where it exposes one, else :data:`FALLBACK_SPECULAR` (a dielectric's 0.04).
"""
from __future__ import annotations

import math

import numpy as np

FALLBACK_SPECULAR = 0.04
FALLBACK_ROUGHNESS = 0.5
_GRID = 16


def bsdf_features(mi, bsdf) -> tuple[np.ndarray, float]:
    """``(specular colour (float64, 3), roughness)`` of a Mitsuba BSDF (the module's table)."""
    if bsdf is None:
        return np.zeros(3), 1.0
    name = _class_name(bsdf)
    kids = _children(mi, bsdf)
    params = mi.traverse(bsdf)
    if name in ("TwoSided", "Mask", "BumpMap", "NormalMap"):
        inner = kids.get("brdf_0") or kids.get("nested_bsdf")
        if isinstance(inner, mi.BSDF):
            return bsdf_features(mi, inner)
    if name == "BlendBSDF" and isinstance(kids.get("bsdf_0"), mi.BSDF) and isinstance(kids.get("bsdf_1"), mi.BSDF):
        w = float(np.mean(_value(mi, kids, params, "weight", 0.5)))
        (sa, ra), (sb, rb) = bsdf_features(mi, kids["bsdf_0"]), bsdf_features(mi, kids["bsdf_1"])
        return (1.0 - w) * sa + w * sb, (1.0 - w) * ra + w * rb
    rule = _RULES.get(name)
    if rule is None:
        return _fallback(mi, bsdf, kids, params)
    return rule(mi, kids, params)


def _class_name(bsdf) -> str:
    """Mitsuba's class of a BSDF as its ``to_string`` opens (``RoughConductor[...``, ``Principled BSDF :``)."""
    text = str(bsdf)
    return text.split("[", 1)[0].split(":", 1)[0].split("\n", 1)[0].strip()


def _children(mi, obj) -> dict:
    """The objects a Mitsuba object holds (nested BSDFs, textures), by the names its traversal gives."""
    found: dict = {}

    class Collect(mi.TraversalCallback):
        def put(self, name, value, flags, *rest):
            if isinstance(value, mi.Object):
                found[name] = value

    obj.traverse(Collect())
    return found


def _value(mi, kids: dict, params, name: str, default) -> np.ndarray:
    """A parameter's value (float64; RGB for a spectrum): a texture's mean, or a plain float parameter."""
    tex = kids.get(name)
    if isinstance(tex, mi.Texture):
        return texture_mean(mi, tex)
    if name in params:
        return np.atleast_1d(np.asarray(params[name], np.float64)).ravel()
    return np.atleast_1d(np.asarray(default, np.float64))


def texture_mean(mi, tex) -> np.ndarray:
    """The mean of a texture's values (float64, 3 or 1): from its parameters where they say it (a constant,
    a bitmap's texels, a checkerboard's two colours), else evaluated on a grid of UVs."""
    p = mi.traverse(tex)
    keys = set(p.keys())
    if "value" in keys:
        return np.atleast_1d(np.asarray(p["value"], np.float64)).ravel()
    if "data" in keys:
        data = np.asarray(p["data"], np.float64)
        return data.reshape(-1, data.shape[-1]).mean(0) if data.ndim >= 2 else np.atleast_1d(data.mean())
    if {"color0.value", "color1.value"} <= keys:
        return 0.5 * (np.asarray(p["color0.value"], np.float64).ravel() + np.asarray(p["color1.value"], np.float64).ravel())
    import drjit as dr
    u, v = np.meshgrid((np.arange(_GRID) + 0.5) / _GRID, (np.arange(_GRID) + 0.5) / _GRID)
    si = dr.zeros(mi.SurfaceInteraction3f, _GRID * _GRID)
    si.uv = mi.Point2f(u.ravel().astype(np.float32), v.ravel().astype(np.float32))
    try:
        out = np.asarray(tex.eval(si), np.float64)
    except (RuntimeError, TypeError):
        out = np.asarray(tex.eval_1(si), np.float64)[None]
    return out.reshape(out.shape[0], -1).mean(1) if out.ndim > 1 else np.atleast_1d(out.mean())


def _rgb(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64).ravel()
    return np.broadcast_to(x if x.size == 3 else x[:1], (3,)).astype(np.float64)


def _alpha(mi, kids, params) -> float | None:
    """The microfacet ``alpha`` (anisotropic: the mean of ``alpha_u`` and ``alpha_v``), or None."""
    if "alpha" in kids or "alpha" in params or "alpha.value" in params:
        return float(np.mean(_value(mi, kids, params, "alpha", 0.0)))
    if "alpha_u" in kids or "alpha_u" in params:
        return 0.5 * float(np.mean(_value(mi, kids, params, "alpha_u", 0.0))
                           + np.mean(_value(mi, kids, params, "alpha_v", 0.0)))
    return None


def _perceptual(alpha: float | None) -> float:
    return 0.0 if alpha is None else float(math.sqrt(max(alpha, 0.0)))


def _dielectric_f0(eta: float) -> float:
    return ((eta - 1.0) / (eta + 1.0)) ** 2 if eta > 0 else 0.0


def _conductor(mi, kids, params):
    eta = _rgb(_value(mi, kids, params, "eta", 0.0))
    k = _rgb(_value(mi, kids, params, "k", 1.0))
    f0 = ((eta - 1.0) ** 2 + k * k) / ((eta + 1.0) ** 2 + k * k)
    spec = f0 * _rgb(_value(mi, kids, params, "specular_reflectance", 1.0))
    return spec, _perceptual(_alpha(mi, kids, params))


def _dielectric(mi, kids, params):
    eta = float(np.mean(_value(mi, kids, params, "eta", 1.5)))
    spec = _dielectric_f0(eta) * _rgb(_value(mi, kids, params, "specular_reflectance", 1.0))
    return spec, _perceptual(_alpha(mi, kids, params))


def _principled(mi, kids, params):
    base = _rgb(_value(mi, kids, params, "base_color", 0.5))
    metallic = float(np.mean(_value(mi, kids, params, "metallic", 0.0)))
    rough = float(np.mean(_value(mi, kids, params, "roughness", 0.5)))
    if "eta" in params:             # a file that gives eta: Mitsuba then derives the dielectric F0 from it
        f0 = _dielectric_f0(float(np.mean(_value(mi, kids, params, "eta", 1.5))))
    else:
        f0 = 0.08 * float(np.mean(_value(mi, kids, params, "specular", 0.5)))
    return f0 * (1.0 - metallic) + base * metallic, rough


def _diffuse(mi, kids, params):
    return np.zeros(3), 1.0


_RULES = {"SmoothDiffuse": _diffuse, "SmoothConductor": _conductor, "RoughConductor": _conductor,
          "SmoothDielectric": _dielectric, "RoughDielectric": _dielectric, "ThinDielectric": _dielectric,
          "SmoothPlastic": _dielectric, "RoughPlastic": _dielectric, "Principled BSDF": _principled}


def _fallback(mi, bsdf, kids, params):
    """The documented fallback (module docstring) for a BSDF the table does not name."""
    flags = int(bsdf.flags())
    F = mi.BSDFFlags
    has = lambda f: bool(flags & int(f))  # noqa: E731
    if not has(F.Glossy) and not has(F.Delta):
        return np.zeros(3), 1.0
    spec = (_rgb(_value(mi, kids, params, "specular_reflectance", 1.0)) if "specular_reflectance" in kids
            else np.full(3, FALLBACK_SPECULAR))
    if not has(F.Glossy):
        return spec, 0.0
    alpha = _alpha(mi, kids, params)
    return spec, FALLBACK_ROUGHNESS if alpha is None else _perceptual(alpha)
