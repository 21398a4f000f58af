"""What the data buys: denoiser quality against the number of training frames, their scene variety and
their share of hard cases.

``python -m studies scaling --config configs/scaling-cpu.yaml [--out DIR] [--target-relmse X]`` (and
``make scaling``) renders (or resumes) a training store and a held-out store of other seeds, trains each
model of the config on nested subsets of the training frames (the same steps for every size, several
seeds), evaluates every run on the same held-out frames, fits ``error(N) = a N^(-b) + c`` per model and
metric (:mod:`studies.scaling_fit`) and writes ``scaling.png``, ``scaling.md`` and ``scaling.json``
(:mod:`studies.scaling_report`). This module holds the settings and the plan; the runs are in
:mod:`studies.scaling_run`.

* **Nested subsets by clip** (:func:`nested_subsets`): the training clips (a still is a clip of one
  frame) in an order drawn from the seed; the subset of each size is the prefix of that order whose
  frame count is nearest to the size's share of the frames. Every smaller set is inside the larger
  one, a clip's frames stay together, and each training seed draws its own order (so the seeds' spread
  includes which frames were drawn, not only the initial weights).
* **Variety** (:func:`family_subsets`): the same number of frames from one scene family (indoor, outdoor)
  or from both (half each), evaluated on each family of the held-out frames.
* **Hard-case share** (:func:`hard_subsets`, :mod:`studies.hard_share`): the same number of frames with
  0%, 10%, 25% ... of them hard-case frames, evaluated on the held-out frames and the hard-case suite.
* **Resumable**: a run folder whose evaluation is written for its settings, its final step and this
  held-out store counts as finished and is not trained or evaluated again; a run interrupted mid-way
  resumes from its checkpoint (``training.loop.train``).
"""
from __future__ import annotations

import dataclasses

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from core.checks import is_int, is_number, known_keys, need, need_int

from training.config import TrainConfig
from training.errors import ConfigError, DataError, UnknownModelError
from .scaling_fit import LOWER_IS_BETTER

SUBSET_SALT = 0x5CA1E
FAMILY_MIX = "both"
REALISM_NONE = "none"         # the realism axis' level without any property: the training config's own frames


TARGET_RANGES = {"relmse": "a relMSE > 0", "smape": "a SMAPE in (0, 1)", "flip": "a FLIP in (0, 1)",
                 "psnr": "a PSNR > 0 dB", "ssim": "an SSIM in (0, 1)", "tpsnr": "a tPSNR > 0 dB"}


def check_targets(targets: dict, where: str, *, flags: bool = False) -> None:
    """Targets to invert (``{metric: value or None}``): known metrics, each a value the metric can take
    (ConfigError naming ``where.metric``; with ``flags``, the command's flag ``where-metric``:
    ``--target-psnr -5``)."""
    known_keys(targets, LOWER_IS_BETTER, where, ConfigError)
    for k, v in targets.items():
        bounded = k in ("smape", "flip", "ssim")
        ok = v is None or (is_number(v, finite=True) and v > 0 and (not bounded or v < 1))
        need(ok, f"{where}-{k}" if flags else f"{where}.{k}", TARGET_RANGES[k] if flags else
             f"null or {TARGET_RANGES[k]}", v, ConfigError)


@dataclass(frozen=True)
class ScalingConfig:
    """A scaling study (``configs/scaling-*.yaml``). ``train_data`` and ``heldout_data``: dataset configs
    (``pipeline.config``; a mapping, or the path of a dataset YAML), trained on their ``train`` and
    evaluated on their ``test`` split; ``models``: TrainConfig settings a run (``model`` required; an
    optional ``label`` names it), over the settings every run shares (``train``); ``subsets``: shares of
    the training frames in (0, 1]; ``seeds``: training seeds (each draws its own nested subsets);
    ``variety``: ``{models: [labels], seeds: [...], frames: N or null}`` (null: the frames of the smaller
    family); ``metrics`` fitted; ``targets``: ``{relmse: X, psnr: Y}`` to invert; ``parallel`` runs at a
    time of ``threads`` torch threads each (0: cores / threads); ``workers``: render workers (null: one a
    core), also the workers of the rendering cost's wall time.

    The hard-case share axis: ``hard_data``, a held-out dataset config (``held_out: true``: the hard-case
    suite, ``configs/hard-cases.yaml``), and ``hard_share: {models: [labels], seeds: [...], frames: N,
    shares: [0, 0.1, 0.25]}``: each model trains on N training frames of which each share are hard-case
    frames (``frames/case`` set; the rest ordinary), at the same steps; every such run and every baseline
    is evaluated on the held-out ordinary frames and on the suite (:func:`hard_subsets`,
    :mod:`studies.hard_share`).

    The realism axis: ``realism: {models: [labels], seeds: [...], suite: DATASET YAML, filters: [box,
    gaussian], levels: {NAME: {scene_gen: {...}, render: {...}}}}``: each level is a property of real scenes
    the generator may lack, given as settings over ``train_data``'s (e.g. ``p_natural_textures: 1``); the
    training store is rendered once a level, from the same seeds (so the same scenes, with and without the
    property: ``scene_gen.phenomena`` draws each from its own stream), and each model trains on every level's
    training frames and on ``train_data``'s own (level ``none``) at the same steps. Every such run and every
    baseline is evaluated on the held-out ordinary frames and on the held-out real-scene suite ``suite``
    (``configs/real-scenes.yaml``) rendered with each pixel filter (:mod:`studies.realism`).
    ``subsets`` may be empty when another axis is given."""

    train_data: dict | str
    heldout_data: dict | str
    models: tuple
    name: str = "scaling"
    out: str | None = None
    subsets: tuple = (0.0625, 0.125, 0.25, 0.5, 1.0)
    seeds: tuple = (0, 1, 2)
    train: dict = field(default_factory=dict)
    variety: dict | None = None
    hard_data: dict | str | None = None
    hard_share: dict | None = None
    realism: dict | None = None
    metrics: tuple = ("relmse", "psnr")
    targets: dict = field(default_factory=dict)
    parallel: int = 0
    threads: int = 1
    flip: bool = False
    resamples: int = 1000
    workers: int | None = None

    def __post_init__(self):
        for k in ("models", "subsets", "seeds", "metrics"):
            object.__setattr__(self, k, tuple(getattr(self, k) or ()))
        s = self.subsets
        need((len(s) >= 1 or self.variety or self.hard_share or self.realism) and all(is_number(v, finite=True) and 0 < v <= 1 for v in s) and len(set(s)) == len(s),
             "scaling.subsets", "a list of distinct shares of the training frames in (0, 1] (empty only beside another "
             "axis: variety, hard_share or realism)", list(s), ConfigError)
        object.__setattr__(self, "subsets", tuple(sorted(float(v) for v in s)))
        need(len(self.seeds) >= 1 and all(is_int(v) and v >= 0 for v in self.seeds) and
             len(set(self.seeds)) == len(self.seeds), "scaling.seeds", "a list of distinct integers >= 0",
             list(self.seeds), ConfigError)
        need(len(self.metrics) >= 1 and all(m in LOWER_IS_BETTER for m in self.metrics), "scaling.metrics",
             f"a list of {sorted(LOWER_IS_BETTER)}", list(self.metrics), ConfigError)
        check_targets(self.targets, "scaling.targets")
        need_int("scaling.parallel", self.parallel, 0, 256, ConfigError)
        need_int("scaling.threads", self.threads, 1, 1024, ConfigError)
        need_int("scaling.resamples", self.resamples, 50, 100_000, ConfigError)
        need(self.workers is None or (is_int(self.workers) and self.workers >= 1), "scaling.workers",
             "null (one a core) or an integer >= 1", self.workers, ConfigError)
        need(isinstance(self.flip, bool), "scaling.flip", "true or false", self.flip, ConfigError)
        need(isinstance(self.name, str) and self.name and "/" not in self.name, "scaling.name",
             "a name without '/'", self.name, ConfigError)
        self.model_plans()
        self.variety_plan()
        self.hard_share_plan()
        self.realism_plan()

    def model_plans(self) -> list[tuple[str, TrainConfig]]:
        """``(label, TrainConfig)`` of each model (seed 0, every clip: the template of its runs)."""
        known_keys(self.train, TrainConfig, "scaling.train", ConfigError, noun="setting(s)")
        need(len(self.models) >= 1, "scaling.models", "a non-empty list of {model: NAME, ...}", self.models,
             ConfigError)
        out = []
        for i, m in enumerate(self.models):
            need(isinstance(m, dict) and "model" in m, f"scaling.models[{i}]", "a mapping with a model name", m,
                 ConfigError)
            m = dict(m)
            label = str(m.pop("label", m["model"]))
            for k in ("seed", "train_clips"):
                need(k not in m and k not in self.train, f"scaling.models[{i}].{k}", "left to the study", k,
                     ConfigError)
            try:
                cfg = TrainConfig.from_dict({**self.train, **m})
            except (ConfigError, UnknownModelError) as e:
                raise ConfigError(f"scaling.models[{i}] ({label}): {e}") from e
            need(cfg.steps >= 1, f"scaling.models[{i}].steps", "an integer >= 1 (a run of 0 steps has no checkpoint "
                 "to evaluate)", cfg.steps, ConfigError)
            out.append((label, cfg))
        labels = [lab for lab, _ in out]
        need(len(set(labels)) == len(labels) and all("/" not in lab for lab in labels), "scaling.models",
             "models with distinct labels (set `label`) without '/'", labels, ConfigError)
        return out

    def only_models(self, labels) -> "ScalingConfig":
        """The study with only the models ``labels`` (``--models``): their runs and the baselines at their spp,
        every axis' model list narrowed to them (runs already finished are read back, so a study stopped
        before its last models reports those it has); ConfigError naming a label the study lacks."""
        have = [lab for lab, _ in self.model_plans()]
        labels = list(dict.fromkeys(labels))
        bad = [lab for lab in labels if lab not in have]
        if bad or not labels:
            raise ConfigError(f"--models must name models of the study {have}, got {labels}")
        models = [m for m, (lab, _) in zip(self.models, self.model_plans()) if lab in labels]
        axes = {}
        for k in ("variety", "hard_share", "realism"):
            v = getattr(self, k)
            if v and v.get("models"):
                kept = [m for m in v["models"] if m in labels]
                axes[k] = {**v, "models": kept} if kept else None
        out = dataclasses.replace(self, models=tuple(models), **axes)
        need(bool(out.subsets or out.variety or out.hard_share or out.realism), "--models",
             "models of at least one axis of the study", labels, ConfigError)
        return out

    def variety_plan(self) -> dict | None:
        """``{"models": [labels], "seeds": [...], "frames": N or None}``, or None without a variety axis."""
        if not self.variety:
            return None
        v = known_keys(self.variety, ("models", "seeds", "frames"), "scaling.variety", ConfigError)
        labels = [lab for lab, _ in self.model_plans()]
        models = list(v.get("models") or labels[:1])
        need(all(m in labels for m in models), "scaling.variety.models", f"labels of scaling.models {labels}",
             models, ConfigError)
        seeds = list(v.get("seeds") or self.seeds)
        need(all(is_int(s) and s >= 0 for s in seeds), "scaling.variety.seeds", "integers >= 0", seeds, ConfigError)
        frames = v.get("frames")
        need(frames is None or (is_int(frames) and frames >= 1), "scaling.variety.frames", "null or an integer >= 1",
             frames, ConfigError)
        return {"models": models, "seeds": seeds, "frames": frames}

    def _axis_runs(self, v: dict, axis: str) -> tuple[list, list]:
        """An axis' ``models`` (labels of ``models``; default all) and ``seeds`` (distinct integers >= 0;
        default the study's), checked."""
        labels = [lab for lab, _ in self.model_plans()]
        models = list(v.get("models") or labels)
        need(all(m in labels for m in models), f"scaling.{axis}.models", f"labels of scaling.models {labels}",
             models, ConfigError)
        seeds = list(v.get("seeds") or self.seeds)
        need(all(is_int(x) and x >= 0 for x in seeds) and len(set(seeds)) == len(seeds), f"scaling.{axis}.seeds",
             "distinct integers >= 0", seeds, ConfigError)
        return models, seeds

    def hard_share_plan(self) -> dict | None:
        """``{"models", "seeds", "frames", "shares"}`` of the hard-case share axis, or None without one."""
        if not self.hard_share:
            return None
        v = known_keys(self.hard_share, ("models", "seeds", "frames", "shares"), "scaling.hard_share", ConfigError)
        models, seeds = self._axis_runs(v, "hard_share")
        need_int("scaling.hard_share.frames", v.get("frames"), 1, 10_000_000, ConfigError)
        shares = v.get("shares") or [0.0, 0.1, 0.25]
        need(isinstance(shares, list) and all(is_number(x, finite=True) and 0 <= x <= 1 for x in shares)
             and len({round(100 * x) for x in shares}) == len(shares) and 0 in shares, "scaling.hard_share.shares",
             "shares of hard-case frames in [0, 1] at least a percent apart, 0 among them (the others are compared "
             "with it)", shares, ConfigError)
        need(self.hard_data is not None, "scaling.hard_data", "a held-out hard-case suite (e.g. "
             "configs/hard-cases.yaml) when hard_share is set", self.hard_data, ConfigError)
        return {"models": models, "seeds": seeds, "frames": int(v["frames"]), "shares": sorted(float(x) for x in shares)}

    def realism_plan(self) -> dict | None:
        """``{"models", "seeds", "suite", "filters", "levels": {name: {"scene_gen", "render"}}}`` of the realism
        axis, or None without one (``levels`` without ``none``, the training config's own frames)."""
        if not self.realism:
            return None
        v = known_keys(self.realism, ("models", "seeds", "suite", "filters", "levels"), "scaling.realism", ConfigError)
        models, seeds = self._axis_runs(v, "realism")
        need(isinstance(v.get("suite"), (str, dict)), "scaling.realism.suite", "the held-out real-scene suite's "
             "dataset config (e.g. configs/real-scenes.yaml)", v.get("suite"), ConfigError)
        filters = list(v.get("filters") or ["box"])
        need(all(f in ("box", "gaussian") for f in filters) and len(set(filters)) == len(filters),
             "scaling.realism.filters", "distinct pixel filters among box, gaussian", filters, ConfigError)
        levels = v.get("levels")
        need(isinstance(levels, dict) and levels and all(isinstance(k, str) and k and k != REALISM_NONE and "/" not in k
                                                         for k in levels), "scaling.realism.levels",
             f"a mapping of level names (not {REALISM_NONE!r}, without '/') to {{scene_gen: {{...}}, render: {{...}}}}",
             levels, ConfigError)
        out = {}
        for name, lv in levels.items():
            lv = known_keys(lv or {}, ("scene_gen", "render"), f"scaling.realism.levels.{name}", ConfigError)
            need(all(isinstance(lv.get(k, {}), dict) for k in ("scene_gen", "render")) and (lv.get("scene_gen") or
                 lv.get("render")), f"scaling.realism.levels.{name}", "settings over the training config's "
                 "(scene_gen: {...} and/or render: {...})", lv, ConfigError)
            out[name] = {"scene_gen": dict(lv.get("scene_gen") or {}), "render": dict(lv.get("render") or {})}
        return {"models": models, "seeds": seeds, "suite": v["suite"], "filters": filters, "levels": out}

    def level_configs(self) -> dict:
        """``{level: DatasetConfig}`` of the realism axis: ``none`` (``train_data`` itself) and each level's
        (``train_data`` with the level's settings over its own, named ``<name>-<level>``); ConfigError naming
        the level where its settings are not valid."""
        r = self.realism_plan()
        base = self._dataset("train_data")
        out = {REALISM_NONE: base}
        from pipeline.config import DatasetConfig
        from pipeline.errors import ConfigError as PipelineConfigError
        for name, lv in (r["levels"] if r else {}).items():
            d = {**base.to_dict(), "name": f"{base.name}-{name}", "out": None,
                 "scene_gen": {**base.scene_gen, **lv["scene_gen"]}, "render": {**base.render, **lv["render"]}}
            try:
                out[name] = DatasetConfig.from_dict(d)
            except PipelineConfigError as e:
                raise ConfigError(f"scaling.realism.levels.{name}: {e}") from e
        return out

    def suite_configs(self) -> dict:
        """``{filter: DatasetConfig}`` of the realism axis' real-scene suite (held out), one per pixel filter:
        the box-filtered store keeps the suite's name, another is ``<name>-<filter>`` (as ``make real-scenes``
        names them, so both share the stores)."""
        r = self.realism_plan()
        if not r:
            return {}
        from pipeline.config import DatasetConfig, load_config
        from pipeline.errors import ConfigError as PipelineConfigError
        try:
            base = load_config(r["suite"]) if isinstance(r["suite"], str) else DatasetConfig.from_dict(r["suite"])
            need(base.held_out, "scaling.realism.suite", "a held-out dataset (held_out: true), whose scenes no "
                 "training config draws", base.name, ConfigError)
            out = {}
            for f in r["filters"]:
                own = base.render.get("filter", "box") == f
                out[f] = base if own else DatasetConfig.from_dict(
                    {**base.to_dict(), "name": f"{base.name}-{f}", "render": {**base.render, "filter": f}})
            return out
        except PipelineConfigError as e:
            raise ConfigError(f"scaling.realism.suite: {e}") from e

    def hard_config(self):
        """The held-out hard-case suite's ``pipeline.config.DatasetConfig``, or None; ConfigError unless it
        is held out (``held_out: true``: seeds no training config draws)."""
        if self.hard_data is None:
            return None
        cfg = self._dataset("hard_data")
        need(cfg.held_out, "scaling.hard_data", "a held-out dataset (held_out: true), whose scenes no training "
             "config draws", cfg.name, ConfigError)
        return cfg

    def _dataset(self, key: str):
        from pipeline.config import DatasetConfig, load_config
        from pipeline.errors import ConfigError as PipelineConfigError
        d = getattr(self, key)
        try:
            return load_config(d) if isinstance(d, str) else DatasetConfig.from_dict(d)
        except PipelineConfigError as e:
            raise ConfigError(f"scaling.{key}: {e}") from e

    def dataset_configs(self) -> tuple:
        """The training and held-out ``pipeline.config.DatasetConfig``."""
        return self._dataset("train_data"), self._dataset("heldout_data")

    def to_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))

    @classmethod
    def from_dict(cls, d) -> "ScalingConfig":
        d = known_keys(d, cls, "scaling", ConfigError)
        for k in ("train_data", "heldout_data", "models"):
            if k not in d:
                raise ConfigError(f"scaling.{k} is required")
        return cls(**d)


def load_scaling_config(path) -> ScalingConfig:
    """Read and check a scaling YAML, its two dataset configs included (before anything is rendered);
    ConfigError naming the file and the field."""
    import yaml
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"scaling config {str(p)!r} is not a file")
    try:
        scfg = ScalingConfig.from_dict(yaml.safe_load(p.read_text()))
        scfg.dataset_configs()
        scfg.hard_config()
        scfg.level_configs()
        write_suite_files(scfg)
        scfg.suite_configs()
        return scfg
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML: {e}") from e
    except (ConfigError, TypeError) as e:
        raise ConfigError(f"{p}: {e}") from e


def write_suite_files(scfg: ScalingConfig, log=None) -> None:
    """The realism axis' suite names the held-out real-scene suite's files (a folder ``real-scenes``, as
    ``configs/real-scenes.yaml`` does): where that folder holds no scene file yet, write them
    (``python -m scene_gen real-scenes``: the same bytes each time), as ``make real-scenes`` does first."""
    r = scfg.realism_plan()
    if not r:
        return
    import yaml

    from pipeline.groups import expand_path
    suite = r["suite"]
    if isinstance(suite, str):
        p = Path(suite)
        if not p.is_file():
            raise ConfigError(f"scaling.realism.suite {suite!r} is not a file")
        suite = yaml.safe_load(p.read_text())
    for g in (suite or {}).get("scenes") or []:
        folder = Path(expand_path(g["file"])) if isinstance(g, dict) and isinstance(g.get("file"), str) else None
        if folder is not None and folder.name == "real-scenes" and not any(folder.glob("*.xml")):
            from scene_gen.real_scenes import write_suite
            (log or print)(f"scaling: writing the real-scene suite's scene files to {folder}")
            write_suite(folder)


# --------------------------------------------------------------------------------------------
# Subsets: clips whole, nested, a function of the seed


def _order(ids, seed: int, salt: int) -> list[int]:
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(salt)]))
    ids = sorted(int(c) for c in ids)
    return [ids[i] for i in rng.permutation(len(ids))]


def _nearest_prefix(order: list[int], frames: dict, want: float) -> list[int]:
    """The prefix of ``order`` (at least one clip) whose frame count is nearest to ``want``."""
    cum = np.cumsum([frames[c] for c in order])
    return order[:int(np.argmin(np.abs(cum - want))) + 1]


def nested_subsets(clip_frames: dict, shares, seed: int) -> list[dict]:
    """Nested subsets of the clips (``clip_frames``: clip id -> its frames) for each share of the frames,
    smallest first: ``[{"share", "frames", "clips"}]``. The clips are ordered by ``seed``; a subset is the
    prefix of that order whose frame count is nearest to ``share`` x all frames, so every subset holds
    the smaller ones and each clip is whole."""
    if not clip_frames:
        raise DataError("no training clip to draw subsets from")
    order = _order(clip_frames, seed, SUBSET_SALT)
    total = sum(clip_frames.values())
    out = []
    for share in sorted(shares):
        clips = _nearest_prefix(order, clip_frames, share * total)
        out.append({"share": float(share), "frames": int(sum(clip_frames[c] for c in clips)), "clips": sorted(clips)})
    return out


def family_subsets(clip_frames: dict, clip_family: dict, frames: int | None, seed: int) -> dict:
    """``frames`` training frames of each scene family alone and of all families mixed (``"both"``, the
    families taking turns, the one with fewer frames so far first): ``{family: {"frames", "clips"}}``.
    ``frames`` None: the frames of the smallest family. A family with fewer frames gives all it has."""
    fams = sorted(set(clip_family.values()))
    if len(fams) < 2:
        raise DataError(f"the training clips are of one scene family ({fams}): the variety axis needs two")
    orders = {f: _order([c for c in clip_frames if clip_family[c] == f], seed, SUBSET_SALT + 1) for f in fams}
    sizes = {f: sum(clip_frames[c] for c in orders[f]) for f in fams}
    n = min(sizes.values()) if frames is None else int(frames)
    out = {f: _nearest_prefix(orders[f], clip_frames, n) for f in fams}
    mixed, taken, pos = [], dict.fromkeys(fams, 0), dict.fromkeys(fams, 0)
    while any(pos[f] < len(orders[f]) for f in fams):
        f = min((f for f in fams if pos[f] < len(orders[f])), key=lambda f: (taken[f], f))
        c = orders[f][pos[f]]
        mixed.append(c)
        pos[f], taken[f] = pos[f] + 1, taken[f] + clip_frames[c]
    out[FAMILY_MIX] = _nearest_prefix(mixed, clip_frames, n)
    return {f: {"frames": int(sum(clip_frames[c] for c in v)), "clips": sorted(v)} for f, v in out.items()}


def hard_subsets(clip_frames: dict, clip_case: dict, frames: int, shares, seed: int) -> dict:
    """For each share: ``frames`` training frames of which that share are hard-case frames (clips whose
    ``case`` is set) and the rest ordinary, ``{share: {"frames", "hard_frames", "clips"}}``. Each kind's
    clips are taken in an order drawn from ``seed`` (so a larger share holds every hard clip of a smaller
    one), the nearest prefix in frames; DataError when the store holds too few of a kind."""
    hard = _order([c for c in clip_frames if clip_case[c]], seed, SUBSET_SALT + 2)
    plain = _order([c for c in clip_frames if not clip_case[c]], seed, SUBSET_SALT + 3)
    out = {}
    for share in sorted(shares):
        want = round(float(share) * frames)
        for pool, n, what in ((hard, want, "hard-case"), (plain, frames - want, "ordinary")):
            have = sum(clip_frames[c] for c in pool)
            if n > have:
                raise DataError(f"scaling.hard_share: {frames} frames at share {share:g} need {n} {what} training "
                                f"frames; the store has {have}")
        h = _nearest_prefix(hard, clip_frames, want) if want else []
        got = sum(clip_frames[c] for c in h)
        p = _nearest_prefix(plain, clip_frames, frames - got) if frames - got > 0 else []
        out[float(share)] = {"frames": int(got + sum(clip_frames[c] for c in p)), "hard_frames": int(got),
                             "clips": sorted(h + p)}
    return out


def clip_table(store, split: str) -> dict[int, dict]:
    """clip id -> ``{"frames": [store frame indices], "family": scene family, "case": hard-case tag}`` of a
    store split (the family from ``frames/kind``, :func:`stores.protocol.scene_kinds`, '' where there is none; the case from
    ``frames/case``, '' for ordinary clips and stores without the column)."""
    try:
        cases = [str(c) for c in store.meta_column("case")]
    except KeyError:
        cases = None
    from stores.protocol import scene_kinds
    kinds, out = scene_kinds(store), {}
    for clip, idx in store.clips(split).items():
        out[int(clip)] = {"frames": [int(i) for i in idx], "family": str(kinds[idx[0]]),
                          "case": cases[idx[0]] if cases else ""}
    return out


# --------------------------------------------------------------------------------------------
# The plan: one job a run


@dataclass(frozen=True)
class Job:
    """One training run (``kind`` ``subset``, ``variety``, ``hard`` or ``realism``) or one baseline evaluation
    (``baseline``): its folder under ``OUT/runs`` (``name``), model ``label``, seed, training frames and
    clips, the subset's ``share`` (of the training frames; for ``hard``, of hard-case frames), the variety
    ``family`` or the realism ``level`` (whose store it trains on), and its TrainConfig as a dict (a baseline: ``method`` and ``spp``, ``baseline_input``)."""
    name: str
    label: str
    kind: str
    seed: int = 0
    frames: int = 0
    clips: tuple = ()
    share: float | None = None
    family: str | None = None
    train_config: dict | None = None
    method: str | None = None
    spp: int | None = None
    baseline_input: str | None = None
    level: str | None = None

    def config(self) -> TrainConfig:
        return TrainConfig.from_dict(self.train_config)

    def to_dict(self) -> dict:
        """Plain data; ``level`` only where set (a record written before the realism axis still matches)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()
                if not (k == "level" and v is None)}


def _train_job(label: str, cfg: TrainConfig, kind: str, seed: int, sub: dict, name: str, **kw) -> Job:
    run_cfg = cfg.replace(seed=int(seed), train_clips=list(sub["clips"]))
    return Job(name=f"{label}/{name}", label=label, kind=kind, seed=int(seed), frames=int(sub["frames"]),
               clips=tuple(sub["clips"]), train_config=run_cfg.to_dict(), **kw)


def hard_share_jobs(scfg: ScalingConfig, frames: dict, cases: dict, record: dict) -> list[Job]:
    """The runs of the hard-case share axis (``kind`` ``hard``), seed by seed, recording the subsets drawn
    in ``record["hard_share"]``."""
    h = scfg.hard_share_plan()
    if not h:
        return []
    by_label = dict(scfg.model_plans())
    jobs, record["hard_share"] = [], {}
    for seed in h["seeds"]:
        subs = hard_subsets(frames, cases, h["frames"], h["shares"], seed)
        counts = [v["hard_frames"] for v in subs.values()]
        if len(set(counts)) < len(counts):
            raise DataError(f"scaling.hard_share: the shares {list(subs)} of {h['frames']} frames give "
                            f"{counts} hard-case frames; two shares with the same count would be the same run: "
                            "use shares further apart or more frames")
        record["hard_share"][str(seed)] = {str(k): v for k, v in subs.items()}
        for label in h["models"]:
            for share, sub in subs.items():
                jobs.append(_train_job(label, by_label[label], "hard", seed, sub,
                                       f"hard-{round(100 * share):03d}pct-n{sub['frames']:05d}-s{seed}", share=share))
    return jobs


def realism_jobs(scfg: ScalingConfig, level_tables: dict, record: dict) -> list[Job]:
    """The runs of the realism axis (``kind`` ``realism``): each model and seed on every training clip of each
    level's store (``level_tables``: level -> :func:`clip_table` of its training split), model by model (a
    study stopped early has whole models), level ``none`` first; DataError when the levels' stores hold other clips or frames (they are the same scenes)."""
    r = scfg.realism_plan()
    if not r:
        return []
    frames = {lv: {c: len(v["frames"]) for c, v in t.items()} for lv, t in level_tables.items()}
    ref = frames[REALISM_NONE]
    for lv, f in frames.items():
        if f != ref:
            raise DataError(f"scaling.realism: level {lv!r}'s training store holds {sum(f.values())} frames in "
                            f"{len(f)} clips, level {REALISM_NONE!r}'s {sum(ref.values())} in {len(ref)}: the "
                            "levels must render the same scenes (change only scene_gen and render settings)")
    sub = {"frames": sum(ref.values()), "clips": sorted(ref)}
    record["realism"] = {"levels": list(level_tables), "frames": sub["frames"], "clips": len(sub["clips"])}
    by_label = dict(scfg.model_plans())
    return [_train_job(label, by_label[label], "realism", seed, sub, f"realism-{lv}-n{sub['frames']:05d}-s{seed}",
                       level=lv)
            for label in r["models"] for seed in r["seeds"] for lv in level_tables]


def baseline_jobs(plans) -> list[Job]:
    """The noisy input and OIDN at each (spp, baseline input) of the models (``training.evaluate``)."""
    from training.inputs import KINDS
    from training.models import get
    seen = sorted({(cfg.spp, KINDS[get(cfg.model).inputs.kind].baseline_input) for _, cfg in plans})
    return [Job(name=f"baselines/{m}-{spp}spp-{b}", label=f"{m} @{spp}spp", kind="baseline", method=m, spp=int(spp),
                baseline_input=b) for spp, b in seen for m in ("input", "oidn")]


def plan(scfg: ScalingConfig, table: dict, level_tables: dict | None = None) -> tuple[list[Job], dict]:
    """Every job of the study over the training clips ``table`` (:func:`clip_table`), and the record of the
    subsets drawn (``{"subsets": {seed: [...]}, "variety": {seed: {...}}}``); ``level_tables`` (level ->
    :func:`clip_table` of its store's training split) for the realism axis. Jobs run seed by seed, each
    seed's sizes smallest first, so an early stop leaves whole curves of the first seeds."""
    frames = {c: len(v["frames"]) for c, v in table.items()}
    family = {c: v["family"] for c, v in table.items()}
    plans = scfg.model_plans()
    jobs, record = [], {"training_frames": sum(frames.values()), "training_clips": len(frames),
                        "subsets": {}, "variety": {}}
    for seed in scfg.seeds:
        subs = nested_subsets(frames, scfg.subsets, seed)
        record["subsets"][str(seed)] = subs
        done = set()
        for sub in subs:
            if sub["frames"] in done:               # two shares of a small store gave the same clips
                continue
            done.add(sub["frames"])
            for label, cfg in plans:
                jobs.append(_train_job(label, cfg, "subset", seed, sub, f"n{sub['frames']:05d}-s{seed}",
                                       share=sub["share"]))
    jobs += hard_share_jobs(scfg, frames, {c: v.get("case", "") for c, v in table.items()}, record)
    v = scfg.variety_plan()
    by_label = dict(plans)
    for seed in (v["seeds"] if v else []):
        fs = family_subsets(frames, family, v["frames"], seed)
        record["variety"][str(seed)] = fs
        for label in v["models"]:
            for fam, sub in fs.items():
                jobs.append(_train_job(label, by_label[label], "variety", seed, sub,
                                       f"variety-{fam}-n{sub['frames']:05d}-s{seed}", family=fam))
    jobs += realism_jobs(scfg, level_tables or {REALISM_NONE: table}, record)
    return jobs + baseline_jobs(plans), record
