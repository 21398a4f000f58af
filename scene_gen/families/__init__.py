"""Scene families: one file each in this folder, found by name; the registry of scene kinds.

A family is a module here (``indoor.py``, ``outdoor.py``) whose layout function registers itself::

    @register_family("outdoor", seed_index=1, settings={
        "outdoor_objects": Setting(75, "int", 0, 10000, "meshes placed"),
        "p_sunsky": Setting(0.5, "probability", doc="Mitsuba sunsky, else a procedural HDR probe")})
    def layout_outdoor(rng, r_cam, cfg, fov, res, user_models) -> Layout: ...

Everything else comes from here: the scene kinds (:func:`family_names`) that the dataset config and
the command lines accept (``SceneSpec.kind`` is checked as a family's name only: the spec module sits
below the families, which build specs); the seed of a scene, ``SeedSequence([seed, family.seed_index])``
(``scene_gen.sampling.sample_scene``); and the family's own settings, fields of
``scene_gen.config.SceneGenConfig`` with their defaults and allowed values. Adding a family is adding
a file here (docs/scene-families.md).

``seed_index`` is part of a family's identity: every scene of every dataset made with the family is
drawn from it, so it never changes, and a new family takes an index no family has used (indoor 0,
outdoor 1). :func:`family_names` lists the families in ``seed_index`` order.

Modules in this folder are found with ``pkgutil`` and imported in name order the first time a family
is looked up (names starting with ``_`` are skipped); a family module imports what families share
(``scene_gen.layout``, ``materials``, ``cameras``, ...), never ``scene_gen.config`` or
``scene_gen.sampling``, which are built on this registry. This module imports nothing of ``scene_gen``
but its errors.
"""
from __future__ import annotations

import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import Callable

from scene_gen.errors import ConfigError

SETTING_KINDS = ("int", "probability")


@dataclass(frozen=True)
class Setting:
    """A family's own setting, a field of ``SceneGenConfig``: its default and allowed values, ``kind``
    ``int`` (an integer in ``[lo, hi]``) or ``probability`` (a number in [0, 1]). ``newer``: a setting added
    after stores were made without it, recorded in a store's config only when not its default (so those
    stores still resume)."""
    default: int | float
    kind: str = "int"
    lo: int | None = None
    hi: int | None = None
    doc: str = ""
    newer: bool = False

    def __post_init__(self):
        if self.kind not in SETTING_KINDS:
            raise ConfigError(f"a scene family setting's kind must be one of {SETTING_KINDS}, got {self.kind!r}")
        if self.kind == "int" and not (isinstance(self.lo, int) and isinstance(self.hi, int) and self.lo <= self.hi):
            raise ConfigError(f"an 'int' scene family setting needs integers lo <= hi, got {self.lo!r}, {self.hi!r}")


@dataclass(frozen=True)
class Family:
    """A registered scene family: ``layout(rng, r_cam, cfg, fov, res, user_models) -> Layout``."""
    name: str
    seed_index: int
    layout: Callable
    settings: dict = field(default_factory=dict)      # setting name -> Setting

    @property
    def module(self) -> str:
        return self.layout.__module__


FAMILIES: dict[str, Family] = {}
_order: tuple[str, ...] = ()       # FAMILIES' names by seed_index (one tuple object until a family registers)
_found = False                     # the family modules have been imported
_settings_read = False             # scene_gen.config has built SceneGenConfig from the settings


def register_family(name: str, *, seed_index: int, settings: dict[str, Setting] | None = None):
    """Decorator: register a layout function as the scene family ``name`` drawn with ``seed_index``."""
    def deco(fn):
        global _order
        fam = Family(name, seed_index, fn, dict(settings or {}))
        _check_new(fam)
        FAMILIES[name] = fam
        _order = tuple(sorted(FAMILIES, key=lambda n: FAMILIES[n].seed_index))
        return fn
    return deco


def _check_new(fam: Family) -> None:
    name, where = fam.name, f"scene family {fam.name!r} ({fam.module})"
    if not isinstance(name, str) or not name.isidentifier() or name != name.lower():
        raise ConfigError(f"a scene family's name must be a lower-case identifier, got {name!r}")
    if isinstance(fam.seed_index, bool) or not isinstance(fam.seed_index, int) or fam.seed_index < 0:
        raise ConfigError(f"{where}: seed_index must be an integer >= 0, got {fam.seed_index!r}")
    others = [f for f in FAMILIES.values() if f.name != name]
    old = FAMILIES.get(name)
    if old is not None and (old.module, old.layout.__qualname__) != (fam.module, fam.layout.__qualname__):
        raise ConfigError(f"scene family {name!r} is already registered by {old.module}")
    taken = {f.seed_index: f.name for f in others}
    if fam.seed_index in taken:
        raise ConfigError(f"{where}: seed_index {fam.seed_index} is already the scene family "
                          f"{taken[fam.seed_index]!r}'s; take one no family has used")
    for s, v in fam.settings.items():
        if not isinstance(v, Setting):
            raise ConfigError(f"{where}: setting {s!r} must be a scene_gen.families.Setting, got {type(v).__name__}")
        owner = next((f.name for f in others if s in f.settings), None)
        if owner is not None:
            raise ConfigError(f"{where}: setting {s!r} is already the scene family {owner!r}'s")
    if _settings_read and fam.settings != (old.settings if old else {}):
        raise ConfigError(f"{where} brings settings after scene_gen.config was built from the families' "
                          f"settings: put the family in a module of {__name__}, where it is found first")


def _discover() -> None:
    """Import every module of this folder once (name order); each registers its family."""
    global _found
    if _found:
        return
    for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if not m.name.startswith("_"):
            importlib.import_module(f"{__name__}.{m.name}")
    _found = True


def family_names() -> tuple[str, ...]:
    """The registered scene kinds in ``seed_index`` order, e.g. ``("indoor", "outdoor")`` (the same
    tuple object on every call until a family registers)."""
    _discover()
    return _order


def get_family(name: str) -> Family:
    """The registered family ``name``; ConfigError naming the known ones for any other."""
    _discover()
    fam = FAMILIES.get(name) if isinstance(name, str) else None
    if fam is None:
        raise ConfigError(f"scene kind must be one of {_order}, got {name!r}")
    return fam


def family_settings() -> dict[str, Setting]:
    """Every family's own settings (setting name -> Setting), families in ``seed_index`` order."""
    global _settings_read
    _discover()
    _settings_read = True
    return {s: v for n in _order for s, v in FAMILIES[n].settings.items()}
