"""The scene groups of a dataset config (``scenes:``): which scenes, how many, of how many frames, and
where they come from: a family of the generator (``kind``, with hard cases drawn at rates) or a user's
Mitsuba scene files (``file``: a file or a folder of them, ``scene_gen.scene_files``); and the seeds that
make a scene's draws a function of the root seed and its index alone.

A file group::

    scenes:
      - {file: path/to/scene.xml, count: 4, frames: 1, camera: {jitter: 0.05}}
      - {file: path/to/folder/, frames: 8}          # count: one scene a file

Scene ``j`` of a file group is the group's file ``j % n`` (its ``n`` files in name order), so ``count``
defaults to ``n``. ``camera`` holds ``scene_gen.scene_files.CameraSettings`` (how cameras vary around the
file's sensor; ``origin``/``target``/``fov`` where the file has no sensor). A path may use ``~`` and
environment variables and is relative to the current folder. Each file's content hash
(``scene_gen.scene_files.content_hash``) is part of the dataset's content, so resuming a store whose
files changed is refused (``pipeline.dataset.check_existing_store``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from core.checks import is_number, need, need_int
from pipeline.errors import ConfigError
from scene_gen.families import family_names

HELD_OUT_SEEDS = 2 ** 31         # held-out datasets' scene seeds lie in [2**31, 2**32), every other's below
CASE_DRAW = 0xCA5E               # SeedSequence([scene seed, CASE_DRAW]) draws a scene's hard case (``cases``)


def scene_seed(root_seed: int, index: int, held_out: bool = False) -> int:
    """Seed of scene ``index``: ``SeedSequence([root_seed, index])``'s first word halved, an int in
    [0, 2**31); for a held-out dataset (``held_out: true``) the same plus 2**31, in [2**31, 2**32). No
    dataset that is not held out can draw a held-out scene, whatever its root seed (``held_out``'s
    docstring in :class:`DatasetConfig`)."""
    ss = np.random.SeedSequence([int(root_seed), int(index)])
    return int(ss.generate_state(1, np.uint32)[0] >> 1) + (HELD_OUT_SEEDS if held_out else 0)


def draw_case(seed: int, cases: dict) -> str:
    """The hard case of the scene of ``seed`` under the rates ``cases`` (case tag -> probability, summing
    to at most 1): one uniform number from the scene's own stream ``SeedSequence([seed, CASE_DRAW])``
    against the rates' cumulative sums in the order of the tags' names ('' when it falls past them), so
    a scene's case depends on its seed and the rates alone, never on workers, task order or the order
    the config lists the cases in."""
    u = float(np.random.default_rng(np.random.SeedSequence([int(seed), CASE_DRAW])).random())
    edge = 0.0
    for tag in sorted(cases):
        edge += float(cases[tag])
        if u < edge:
            return tag
    return ""


def expand_path(path: str) -> str:
    """A group's ``file`` with ``~`` and environment variables expanded; ``$DENOISE_DATA`` is the data folder
    (``data`` where the variable is unset, as for stores: ``DatasetConfig.store_path``)."""
    text = os.path.expanduser(str(path))
    if "DENOISE_DATA" not in os.environ:
        text = text.replace("${DENOISE_DATA}", "data").replace("$DENOISE_DATA", "data")
    return os.path.expandvars(text)


@dataclass(frozen=True)
class SceneGroup:
    """``count`` scenes of one ``kind``, each with ``frames`` frames (1 = a still, > 1 = a clip), with the
    hard case(s) ``case`` applied to every scene (``scene_gen.cases``: a name, or names joined by commas;
    None: none), or a case drawn for each scene at the rates ``cases`` (``{sun: 0.1, fireflies: 0.1}``:
    each scene gets at most one key, a case or a combination of cases joined by commas, with that
    probability, and none with the rest; :func:`draw_case`). With ``file`` the scenes are a user's scene
    files (the module docstring): ``kind`` is ``file``, ``count`` defaults to the number of files, and
    ``camera`` says how the cameras vary. Two file groups over files of different content compare equal as
    dataclasses (the content is found, not a field); :meth:`to_dict` carries the hashes, and the dataset's
    ``content_dict`` with it, which a resume compares."""
    kind: str = ""
    count: int | None = None
    frames: int = 1
    case: str | None = None
    cases: dict | None = None
    file: str | None = None
    camera: dict | None = None

    def validate(self, where: str) -> None:
        if self.file is not None:
            self._validate_file(where)
        else:
            kinds = family_names()
            need(self.kind in kinds, f"{where}.kind", f"one of {kinds}", self.kind, ConfigError)
            if self.camera is not None:
                raise ConfigError(f"{where}.camera is a scene file group's (file: PATH); a generated scene draws "
                                  "its own cameras")
        need_int(f"{where}.count", self.count, 1, 10_000_000, ConfigError, numpy=True)
        need_int(f"{where}.frames", self.frames, 1, 10_000, ConfigError, numpy=True)
        if self.case is not None and self.cases is not None:
            raise ConfigError(f"{where}: give case (every scene) or cases (drawn at rates), not both")
        if self.case is not None:
            self._check_case(self.case, f"{where}.case")
        if self.cases is not None:
            object.__setattr__(self, "cases", self._check_rates(self.cases, f"{where}.cases"))

    def _validate_file(self, where: str) -> None:
        """A file group: its files found and hashed (``files``), its camera settings checked, ``kind`` set to
        ``file`` and ``count`` to the number of files where not given."""
        from scene_gen import scene_files
        from scene_gen.errors import SceneFileError
        need(isinstance(self.file, str) and self.file.strip() != "", f"{where}.file",
             "a Mitsuba scene file or a folder of them", self.file, ConfigError)
        need(self.kind in ("", scene_files.KIND), f"{where}.kind", f"{scene_files.KIND!r} or absent for a file group",
             self.kind, ConfigError)
        if self.case is not None or self.cases is not None:
            raise ConfigError(f"{where}: hard cases (case, cases) are the generator's; a scene file renders as it is")
        try:
            paths = scene_files.scene_list(expand_path(self.file))
            files = tuple((str(p), scene_files.content_hash(p)) for p in paths)
            settings = scene_files.CameraSettings.from_dict(self.camera, f"{where}.camera")
        except SceneFileError as e:
            raise ConfigError(f"{where}.file: {e}") from None
        object.__setattr__(self, "kind", scene_files.KIND)
        object.__setattr__(self, "_files", files)
        object.__setattr__(self, "_camera", settings)
        if self.count is None:
            object.__setattr__(self, "count", len(files))

    @property
    def files(self) -> tuple[tuple[str, str], ...]:
        """A file group's scene files: ``(absolute path, content hash)`` in name order; () for a generated one."""
        return getattr(self, "_files", ())

    def file_source(self, j: int) -> dict | None:
        """What scene ``j`` of a file group is made from (``pipeline.tasks.make_spec``'s ``source``): the file's
        ``path`` and ``sha256`` and the group's ``camera`` settings; None for a generated group."""
        if not self.files:
            return None
        path, sha = self.files[j % len(self.files)]
        return {"path": path, "sha256": sha, "camera": self._camera.to_dict()}

    def to_dict(self) -> dict:
        """Plain data; ``case`` and ``cases`` only when set (stores made before they existed still resume); a
        file group with its files' content hashes (a resume against changed files is refused)."""
        if self.files:
            return {"file": self.file, "count": self.count, "frames": self.frames,
                    **({"camera": dict(self.camera)} if self.camera else {}),
                    "sha256": [h for _, h in self.files]}
        return {"kind": self.kind, "count": self.count, "frames": self.frames, **({"case": self.case} if self.case else {}),
                **({"cases": dict(self.cases)} if self.cases else {})}

    def _check_case(self, case, where: str) -> str:
        from scene_gen.cases import case_tag, check_kind
        from scene_gen.errors import SceneGenError
        try:
            check_kind(case, self.kind)
            return case_tag(case)
        except SceneGenError as e:
            raise ConfigError(f"{where}: {e}") from e

    def _check_rates(self, cases, where: str) -> dict:
        """``cases`` as {case tag: rate}: known names, each rate in [0, 1], summing to at most 1."""
        need(isinstance(cases, dict) and len(cases) > 0, where,
             "a mapping of hard-case names (or names joined by commas) to rates in [0, 1]", cases, ConfigError)
        out = {}
        for name, rate in cases.items():
            tag = self._check_case(name, f"{where}.{name}")
            need(is_number(rate, finite=True) and 0.0 <= rate <= 1.0, f"{where}.{name}", "a rate in [0, 1]", rate,
                 ConfigError)
            if tag in out:
                raise ConfigError(f"{where}: case {tag!r} is given twice")
            out[tag] = float(rate)
        total = sum(out.values())
        if total > 1.0 + 1e-9:
            raise ConfigError(f"{where}: the rates sum to {total:.12g}, above 1; a scene takes at most one case, "
                              "so they must sum to at most 1")
        return out

    @property
    def case_tag(self) -> str:
        """The case names every scene of the group has, as ``SceneSpec.case`` records them ('' for none,
        and for a group that draws its cases: :meth:`scene_case`)."""
        from scene_gen.cases import case_tag
        return case_tag(self.case)

    def scene_case(self, seed: int) -> str:
        """The case tag of this group's scene of ``seed``: ``case``, or the one drawn at ``cases``' rates."""
        return draw_case(seed, self.cases) if self.cases else self.case_tag
