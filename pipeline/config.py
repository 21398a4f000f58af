"""The dataset configuration: one YAML file → a validated, frozen :class:`DatasetConfig`.

Everything is checked when the file is loaded, before a cluster starts or a pixel is rendered: an
unknown key or a bad value raises :class:`~pipeline.errors.ConfigError` whose message names the
field (``dataset.scenes[1].count``) and its allowed range. The sub-sections ``render`` and
``scene_gen`` are validated by their owners (:class:`pipeline.render.RenderConfig`,
:class:`scene_gen.config.SceneGenConfig`), so their messages name their fields the same way.

YAML layout (every key optional except ``scenes``; see ``configs/default.yaml``)::

    name: default                # store name: <out or $DENOISE_DATA>/<name>.zarr
    seed: 1                      # root seed: scene i's seed = SeedSequence([seed, i])
    out: null                    # store path or fsspec URL (the CLI's --out wins)
    resolution: [32, 32]         # (W, H) pixels, or one int for a square
    scenes:                      # groups in order; scene indices run across the groups
      - {kind: indoor,  count: 2}            # stills
      - {kind: outdoor, count: 1, frames: 4} # 4-frame clips
    render: {spp: 8, layer_levels: 6, ref_spp: 4096}   # RenderConfig fields (not res)
    scene_gen: {}                # SceneGenConfig fields
    store: {}                    # passed to the store writer (compression, chunks)
    split: null                  # scene split fractions (default train 0.8 / val 0.1 / test 0.1)
    clip_ids: balanced           # how scenes get their clip ids, hence their split (see below)
    held_out: false              # true: scene seeds from the held-out space; the split is {test: 1} (see below)
    tasks: {retries: 2, split_streams: null, reference_resources: null}
    cluster: {kind: local, workers: null, threads_per_worker: 1, ...}

Frames are numbered in that order: scene 0's frames, then scene 1's, ... A frame's bytes depend only
on (seed, scene index, frame index, render config), never on workers or task order.

Splits are by scene: the store's readers put a scene in the split that ``stores.reader.split_of_clip``
gives its clip id (a hash of the id against the split fractions). ``clip_ids: balanced`` (the default)
chooses each scene's clip id so that split is the one of a balanced assignment: round(fraction x
scenes) scenes each, at least one in every split with a positive fraction once there are as many
scenes as such splits, the scenes shuffled by ``SeedSequence([seed, 0x5b17])``. ``clip_ids:
scene_seed`` uses the scene seed as clip id (stores made before ``clip_ids`` existed; their split is
the bare hash, which leaves small stores without val or test scenes). Resuming such a store keeps it.

**Hard cases** (``scene_gen.cases``): a scene group takes ``case: NAME`` (every scene of the group) or
``cases: {sun: 0.1, fireflies: 0.1, zero-albedo: 0.1, thin: 0.05}`` (each scene draws at most one key
from its own seed at those rates, :func:`pipeline.groups.draw_case`; a key may join several names with commas, a
combination; the rest of the scenes are ordinary). ``frames/case`` records every frame's.

**Held-out datasets** (``held_out: true``, e.g. the hard-case suite ``configs/hard-cases.yaml``) take
their scene seeds from [2**31, 2**32) and every other dataset from [0, 2**31) (:func:`pipeline.groups.scene_seed`), so
no training config, whatever its root seed, draws a held-out scene; a held-out dataset's split is
``{test: 1}`` (the default there; any other is refused), and ``python -m training train`` refuses a store
that records ``held_out``.

Before anything runs, a frame must fit in a worker's memory: :func:`frame_bytes` (its arrays as
rendered, twice: the parts and their store copy in the write task) against the memory of one
worker (``cluster.memory_limit``, else this machine's memory over the workers). Loading a config
does not check it, since its workers are only known once the command line is (``--scheduler``,
``--workers``): ``python -m pipeline dataset`` checks :meth:`DatasetConfig.check_memory` before it
starts a LocalCluster or batch jobs, and the workers' own memory limits once connected.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import ConfigError
from core.checks import is_int, is_number, known_keys, need, need_int
from pipeline.groups import SceneGroup, scene_seed
from stores.schema import StoreLayout

CLIP_ID_SCHEMES = ("balanced", "scene_seed")
SPLIT_SHUFFLE = 0x5B17           # SeedSequence([seed, SPLIT_SHUFFLE]) shuffles the balanced split
CLIP_ID_STRIDE = 2 ** 31         # clip id candidates: scene_seed + j * stride (distinct seeds, distinct ids)
MAX_CLIP_ID_TRIES = 1_000_000
CLUSTER_KINDS = ("local", "scheduler", "slurm", "pbs")
MAX_RES = 16384
STORE_KEYS = frozenset(StoreLayout.encoding_fields())   # what `dataset.store` may set


@dataclass(frozen=True)
class TaskConfig:
    """How the graph is cut into tasks and how failures are handled.

    ``split_streams``: inputs, sample layers and reference of a frame are three tasks (references can
    then run on other workers, e.g. GPU ones); ``false``: one task renders the whole frame, so its
    scene is built and its kernels compiled once, where three tasks on three workers would each pay
    for them; ``null`` (default): split exactly when ``reference_resources`` is set. Measured on 2
    cores (issue 13): the default config 95.3 s whole-frame against 93.9 s split (within 2%), the four
    end-to-end stills 25.3/26.3 against 25.5/26.7 s, the dask bench 1.76-1.80x of one worker against
    1.59-1.69x; split when a dataset has fewer frames than workers. ``retries``: extra attempts of a
    failed task (transient failures) before the frame is recorded as failed. ``reference_resources``: Dask worker resources a reference task
    needs, e.g. ``{GPU: 1}`` (workers must then advertise them: ``dask worker --resources GPU=1``).
    """
    retries: int = 2
    split_streams: bool | None = None
    reference_resources: dict | None = None

    @property
    def split(self) -> bool:
        """Whether a frame's streams are separate tasks (``split_streams``, resolved)."""
        return bool(self.reference_resources) if self.split_streams is None else self.split_streams

    def validate(self) -> None:
        p = "dataset.tasks"
        need_int(f"{p}.retries", self.retries, 0, 100, ConfigError, numpy=True)
        need(self.split_streams is None or isinstance(self.split_streams, bool), f"{p}.split_streams",
             "true, false or null (split exactly when reference_resources is set)", self.split_streams, ConfigError)
        r = self.reference_resources
        if r is not None:
            need(isinstance(r, dict) and len(r) > 0
                 and all(isinstance(k, str) and is_number(v) and v > 0 for k, v in r.items()),
                 f"{p}.reference_resources", "null or a mapping of resource name to a number > 0 (e.g. {GPU: 1})",
                 r, ConfigError)
            need(self.split, f"{p}.split_streams",
                 "true when reference_resources is set (the reference must be its own task)",
                 self.split_streams, ConfigError)


@dataclass(frozen=True)
class ClusterConfig:
    """Where the graph runs (the CLI's ``--scheduler``/``--workers`` override ``kind``/``address``/``workers``).

    - ``local``: a ``LocalCluster`` of ``workers`` processes (default: one per CPU core) with
      ``threads_per_worker`` threads each (drjit's thread pool is sized to match), serving the dashboard
      at ``dashboard_address``.
    - ``scheduler``: connect to a running scheduler at ``address`` (``tcp://host:8786``).
    - ``slurm`` / ``pbs``: start ``jobs`` batch jobs with dask-jobqueue (``pip install dask-jobqueue``);
      ``jobqueue`` holds the keyword arguments of ``SLURMCluster`` / ``PBSCluster`` (cores, memory,
      walltime, queue, account, job_extra_directives, ...).

    ``gpus`` (``local``): ``auto`` gives one worker per GPU that ``nvidia-smi -L`` lists (within the
    ``CUDA_VISIBLE_DEVICES`` of the command), each seeing only its own (``CUDA_VISIBLE_DEVICES``) and
    holding the worker resource ``GPU: 1``, and no CPU render workers (a dataset is rendered by one
    backend, so its bytes do not depend on which worker took a frame); none: the CPU workers above.
    ``null`` or 0: CPU workers even where GPUs are; an integer N: the first N GPUs; a list: those
    device ids. Batch jobs ask for GPUs with ``jobqueue.gpus_per_job`` (``pipeline.jobs.job_settings``).

    ``dashboard_address`` without a host (``:8787``) binds to 127.0.0.1; ``security`` holds
    ``distributed.security.Security`` settings (``pipeline.cluster_settings.make_security``) for TLS.
    """
    kind: str = "local"
    address: str | None = None
    workers: int | None = None
    threads_per_worker: int = 1
    memory_limit: str | int = "auto"
    dashboard_address: str | None = "127.0.0.1:8787"
    connect_timeout: float = 10.0
    jobs: int = 1
    jobqueue: dict = field(default_factory=dict)
    security: dict | None = None
    gpus: str | int | list | None = "auto"

    def validate(self) -> None:
        p = "dataset.cluster"
        need(self.kind in CLUSTER_KINDS, f"{p}.kind", f"one of {CLUSTER_KINDS}", self.kind, ConfigError)
        address_ok = isinstance(self.address, str) and "://" in self.address
        if self.kind == "scheduler":
            need(address_ok, f"{p}.address", "a scheduler address like tcp://host:8786 when kind is 'scheduler'",
                 self.address, ConfigError)
        else:
            need(self.address is None or address_ok, f"{p}.address", "null or a scheduler address like tcp://host:8786",
                 self.address, ConfigError)
        need(self.workers is None or (is_int(self.workers, numpy=True) and 1 <= self.workers <= 4096), f"{p}.workers",
             "null (one per core) or an integer in [1, 4096]", self.workers, ConfigError)
        need_int(f"{p}.threads_per_worker", self.threads_per_worker, 1, 1024, ConfigError, numpy=True)
        m = self.memory_limit
        need((isinstance(m, str) and m != "") or (is_int(m, numpy=True) and m >= 0), f"{p}.memory_limit",
             "'auto', a size like '4GiB', or a number of bytes >= 0", m, ConfigError)
        need(self.dashboard_address is None or isinstance(self.dashboard_address, str), f"{p}.dashboard_address",
             "null (no dashboard) or an address like '127.0.0.1:8787'", self.dashboard_address, ConfigError)
        if self.dashboard_address is not None:
            parse_dashboard(self.dashboard_address, f"{p}.dashboard_address")
        t = self.connect_timeout
        need(is_number(t, finite=True) and 0 < t <= 3600, f"{p}.connect_timeout", "a number of seconds in (0, 3600]",
             t, ConfigError)
        need_int(f"{p}.jobs", self.jobs, 1, 100_000, ConfigError, numpy=True)
        need(isinstance(self.jobqueue, dict) and all(isinstance(k, str) for k in self.jobqueue), f"{p}.jobqueue",
             "a mapping of dask-jobqueue keyword arguments", self.jobqueue, ConfigError)
        g = self.gpus
        need(g is None or g == "auto" or (is_int(g, numpy=True) and 0 <= g <= 1024)
             or (isinstance(g, list) and g and len(set(map(str, g))) == len(g)
                 and all(is_int(x, numpy=True) and 0 <= x < 1024 for x in g)),
             f"{p}.gpus", "'auto', null, a count in [0, 1024] or a list of distinct device ids", g, ConfigError)
        if self.security is not None:
            check_security(self.security, f"{p}.security")
        if self.kind in ("slurm", "pbs"):
            for k in ("cores", "memory"):
                need(k in self.jobqueue, f"{p}.jobqueue.{k}", f"set for kind {self.kind!r} (dask-jobqueue needs it)",
                     self.jobqueue.get(k), ConfigError)


# cluster.security keys: distributed.security.Security's settings that a YAML file can hold
SECURITY_FILES = ("tls_ca_file", "tls_client_cert", "tls_client_key", "tls_scheduler_cert",
                  "tls_scheduler_key", "tls_worker_cert", "tls_worker_key")
SECURITY_KEYS = ("require_encryption", *SECURITY_FILES, "tls_ciphers", "tls_min_version", "tls_max_version")
TLS_VERSIONS = ("TLSv1_2", "TLSv1_3")


def check_security(sec, where: str = "dataset.cluster.security") -> None:
    """Check the shape of ``cluster.security`` (no file is opened; ``pipeline.cluster_settings.make_security``
    reads them): a mapping of ``SECURITY_KEYS`` with ``tls_ca_file`` and ``tls_client_cert`` set.
    Raises :class:`ConfigError` naming the key."""
    need(isinstance(sec, dict), where, f"a mapping of distributed TLS settings ({', '.join(SECURITY_KEYS)})", sec,
         ConfigError)
    known_keys(sec, SECURITY_KEYS, where, ConfigError)
    for k in SECURITY_FILES + ("tls_ciphers",):
        v = sec.get(k)
        need(v is None or (isinstance(v, str) and v.strip() != ""), f"{where}.{k}", "a file path (a string)", v,
             ConfigError)
    for k in ("tls_ca_file", "tls_client_cert"):
        if not sec.get(k):
            raise ConfigError(f"{where}.{k} must be set: a shared scheduler speaks mutual TLS, so the client "
                              "needs the CA certificate (tls_ca_file) and its own certificate (tls_client_cert, "
                              "plus tls_client_key unless the key is in that file)")
    r = sec.get("require_encryption")
    need(r is None or isinstance(r, bool), f"{where}.require_encryption", "true or false", r, ConfigError)
    for k in ("tls_min_version", "tls_max_version"):
        v = sec.get(k)
        need(v is None or v in TLS_VERSIONS, f"{where}.{k}", f"one of {list(TLS_VERSIONS)}", v, ConfigError)


def parse_dashboard(address: str, where: str = "dataset.cluster.dashboard_address") -> tuple[str, int]:
    """``(host, port)`` of a dashboard address (``host:port``, ``:port`` or ``port``; host '' means
    127.0.0.1, ``pipeline.cluster_settings.dashboard_bind``); :class:`ConfigError` naming ``where`` otherwise."""
    a = str(address).strip()
    host, sep, port = a.rpartition(":")
    if not sep:
        host, port = "", a
    host = host.strip("[]")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"{where} must be host:port (or :port) with a port in 0..65535 (0: any free port), "
                          f"got {address!r}")
    return host, int(port)


def balanced_splits(n: int, fractions: dict, seed: int) -> list[str]:
    """The split of each of ``n`` scenes: ``round(fraction x n)`` each (largest remainders), at least one
    for every split with a positive fraction while ``n`` allows (taken from the largest split), in an
    order shuffled by ``SeedSequence([seed, SPLIT_SHUFFLE])``."""
    names = list(fractions)
    total = float(sum(fractions.values()))
    exact = [n * fractions[k] / total for k in names]
    counts = [int(math.floor(x)) for x in exact]
    for i in sorted(range(len(names)), key=lambda i: (-(exact[i] - counts[i]), i))[: n - sum(counts)]:
        counts[i] += 1
    for i, k in enumerate(names):
        if fractions[k] > 0 and counts[i] == 0:
            j = max(range(len(names)), key=lambda j: (counts[j], -j))
            if counts[j] > 1:
                counts[j] -= 1
                counts[i] += 1
    labels = [k for k, c in zip(names, counts) for _ in range(c)]
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), SPLIT_SHUFFLE]))
    return [labels[i] for i in rng.permutation(n)]


def clip_id_for(seed: int, split: str, fractions: dict) -> int:
    """The clip id the store's split hash puts in ``split`` for a scene of ``seed``
    (``stores.reader.clip_id_in_split``: distinct scene seeds give distinct clip ids)."""
    from stores.reader import clip_id_in_split
    c = clip_id_in_split(seed, split, fractions, stride=CLIP_ID_STRIDE, tries=MAX_CLIP_ID_TRIES)
    if c is not None:
        return c
    raise ConfigError(f"dataset.split: no clip id in {MAX_CLIP_ID_TRIES} tries falls in split {split!r} "
                      f"(fraction {fractions.get(split)}); use a larger fraction")


@dataclass(frozen=True)
class FrameRef:
    """One frame of the dataset: its store index, its scene and its index within the scene's clip,
    and the scene's clip id (``frames/clip_id``: it decides the scene's split)."""
    index: int
    scene: int
    kind: str
    seed: int
    frame: int
    num_frames: int
    clip_id: int | None = None
    case: str = ""                  # hard cases of the scene's group (scene_gen.cases), '' for none
    source: dict | None = None      # a scene file's scene: what it is made from (SceneGroup.file_source)

    @property
    def key(self) -> str:
        """Readable Dask key prefix: ``scene-000042/frame-3``."""
        return f"scene-{self.scene:06d}/frame-{self.frame}"


@dataclass(frozen=True)
class DatasetConfig:
    """A whole dataset: what to generate, how to render it, where to store it and where to run.

    ``render`` and ``scene_gen`` are the validated dicts of :class:`pipeline.render.RenderConfig`
    (without ``res``, which comes from ``resolution``) and :class:`scene_gen.config.SceneGenConfig`.
    """
    scenes: tuple[SceneGroup, ...]
    name: str = "dataset"
    seed: int = 0
    out: str | None = None
    resolution: tuple[int, int] = (32, 32)
    render: dict = field(default_factory=dict)
    scene_gen: dict = field(default_factory=dict)
    store: dict = field(default_factory=dict)
    split: dict | None = None     # scene split fractions, e.g. {train: 0.8, val: 0.1, test: 0.1} (the default)
    clip_ids: str = "balanced"    # CLIP_ID_SCHEMES: how clip ids (hence splits) are chosen (module docstring)
    held_out: bool = False        # scene seeds in the held-out space (scene_seed): never trained on
    tasks: TaskConfig = TaskConfig()
    cluster: ClusterConfig = ClusterConfig()

    def __post_init__(self):
        need(isinstance(self.name, str) and self.name != "" and "/" not in self.name
             and self.name.strip() == self.name, "dataset.name", "a non-empty file name without '/'", self.name,
             ConfigError)
        need(is_int(self.seed, numpy=True) and 0 <= self.seed < 2 ** 63, "dataset.seed", "an integer in [0, 2**63)",
             self.seed, ConfigError)
        need(self.out is None or (isinstance(self.out, str) and self.out != ""), "dataset.out",
             "null or a store path / URL", self.out, ConfigError)
        res = self.resolution
        if is_int(res, numpy=True):
            res = (res, res)
        need(isinstance(res, (tuple, list)) and len(res) == 2
             and all(is_int(r, numpy=True) and 1 <= r <= MAX_RES for r in res),
             "dataset.resolution", f"a positive int or [W, H] of ints in [1, {MAX_RES}]", self.resolution, ConfigError)
        object.__setattr__(self, "resolution", (int(res[0]), int(res[1])))
        need(isinstance(self.scenes, (tuple, list)) and len(self.scenes) > 0, "dataset.scenes",
             "a non-empty list of {kind, count, frames} groups", self.scenes, ConfigError)
        object.__setattr__(self, "scenes", tuple(self.scenes))
        for i, g in enumerate(self.scenes):
            g.validate(f"dataset.scenes[{i}]")
        for n in ("render", "scene_gen", "store"):
            need(isinstance(getattr(self, n), dict), f"dataset.{n}", "a mapping", getattr(self, n), ConfigError)
        if "res" in self.render:
            raise ConfigError("dataset.render.res is not allowed: set dataset.resolution (shared with scene_gen)")
        if self.split is not None:
            sp = self.split
            need(isinstance(sp, dict) and sp and set(sp) <= {"train", "val", "test"}
                 and all(is_number(v) and v >= 0 for v in sp.values()) and sum(sp.values()) > 0, "dataset.split",
                 "null or a mapping of train/val/test to fractions >= 0 with a positive sum", sp, ConfigError)
        need(self.clip_ids in CLIP_ID_SCHEMES, "dataset.clip_ids", f"one of {CLIP_ID_SCHEMES}", self.clip_ids,
             ConfigError)
        need(isinstance(self.held_out, bool), "dataset.held_out", "true or false", self.held_out, ConfigError)
        if self.held_out and self.split is None:            # evaluation only: every scene in the test split
            object.__setattr__(self, "split", {"test": 1.0})
        if self.held_out and (self.split_fractions.get("train", 0) > 0 or self.split_fractions.get("val", 0) > 0):
            raise ConfigError(f"dataset.held_out: a held-out dataset is for evaluation only: its split must be "
                              f"{{test: 1}}, got {self.split_fractions}")
        self.tasks.validate()
        self.cluster.validate()
        lv = self.render.get("layer_levels", 6)     # a dataset's range (render-frame's starts at 0): one message
        need(is_int(lv, numpy=True) and 1 <= lv <= 12, "dataset.render.layer_levels",
             "an integer in [1, 12] (a store holds at least the 1-spp sample layer)", lv, ConfigError)
        rc = self.render_config()   # the owners validate their sections (raise ConfigError naming the field)
        if rc.oracle_spp:
            raise ConfigError(f"dataset.render.oracle_spp must be 0 (the store has no oracle image), got {rc.oracle_spp}")
        self.scene_gen_config()
        self.store_layout()
        # no memory check here: the workers are not known until the CLI has its --scheduler / --workers
        # (the dataset command checks before it starts a LocalCluster or batch jobs, and once connected)

    def check_memory(self, per_worker: int | None = None, where: str | None = None, *,
                     workers: int | None = None) -> None:
        """Raise ConfigError when one frame cannot fit in a worker's memory (``per_worker`` bytes, else
        :func:`worker_memory` of this config's cluster with ``workers`` local workers), naming the
        estimate."""
        need = 2 * frame_bytes(self)
        have, src = ((per_worker, where or "per worker") if per_worker
                     else worker_memory(self.cluster, workers=workers))
        if have and need > have:
            W, H = self.resolution
            fix = "lower the resolution or spp, or give workers more memory"
            local = per_worker is None and self.cluster.kind == "local" and self.cluster.memory_limit in (None, "auto", 0)
            n = workers or self.cluster.workers
            if local and n:                   # the machine's memory split over more workers than fit
                total = have * n
                fits = total // need
                if fits >= 1:
                    fix = (f"use at most {fits} workers (--workers or cluster.workers; {n} asked), or lower the "
                           "resolution or spp")
            raise ConfigError(
                f"dataset.resolution {W}x{H} cannot be rendered: one frame needs about {_gib(need)} "
                f"({need:,} bytes: its arrays of {_gib(frame_bytes(self))}, held twice while it is written), "
                f"and a worker has {_gib(have)} ({src}); {fix}")

    # -- derived -----------------------------------------------------------------------------------
    def render_config(self):
        """The :class:`pipeline.render.RenderConfig` of every frame (``res`` = ``resolution``)."""
        from pipeline.render import RenderConfig
        return RenderConfig.from_dict({**self.render, "res": list(self.resolution)})

    def scene_gen_config(self):
        """The :class:`scene_gen.config.SceneGenConfig` (raises ConfigError naming a bad field)."""
        from scene_gen.config import SceneGenConfig
        from scene_gen.errors import SceneGenError
        try:
            return SceneGenConfig.from_dict(dict(self.scene_gen))
        except SceneGenError as e:
            raise ConfigError(f"dataset.{e}" if str(e).startswith("scene_gen") else f"dataset.scene_gen: {e}") from e

    def store_layout(self):
        """The :class:`stores.schema.StoreLayout` of the dataset (``store`` holds its encoding fields)."""
        from stores.errors import StoreError
        known_keys(self.store, STORE_KEYS, "dataset.store", ConfigError)
        rc = self.render_config()
        try:
            return StoreLayout(num_frames=self.num_frames, height=self.resolution[1], width=self.resolution[0],
                               spp=rc.spp, layer_spp=tuple(2 ** n for n in range(rc.layer_levels)), **self.store)
        except (StoreError, TypeError) as e:
            raise ConfigError(f"dataset.store: {e}") from e

    @property
    def num_scenes(self) -> int:
        return sum(g.count for g in self.scenes)

    @property
    def num_frames(self) -> int:
        return sum(g.count * g.frames for g in self.scenes)

    @property
    def split_fractions(self) -> dict:
        from stores.reader import DEFAULT_SPLIT
        return dict(self.split) if self.split else dict(DEFAULT_SPLIT)

    def scene_clip_ids(self) -> list[int]:
        """Clip id of every scene (``clip_ids`` scheme; see the module docstring)."""
        cached = self.__dict__.get("_clip_ids")
        if cached is not None:
            return list(cached)
        seeds = [scene_seed(self.seed, i, self.held_out) for i in range(self.num_scenes)]
        if self.clip_ids == "scene_seed":
            ids = seeds
        else:
            fr = self.split_fractions
            ids = [clip_id_for(s, k, fr) for s, k in zip(seeds, balanced_splits(len(seeds), fr, self.seed))]
        object.__setattr__(self, "_clip_ids", tuple(ids))
        return ids

    def scene_splits(self) -> list[str]:
        """The split each scene will be read in (``stores.reader.split_of_clip`` of its clip id)."""
        from stores.reader import split_of_clip
        fr = self.split_fractions
        return [split_of_clip(c, fr) for c in self.scene_clip_ids()]

    def frames(self) -> list[FrameRef]:
        """Every frame in store order (scene by scene, frame by frame)."""
        out: list[FrameRef] = []
        ids = self.scene_clip_ids()
        s = 0
        for g in self.scenes:
            for j in range(g.count):
                seed = scene_seed(self.seed, s, self.held_out)
                case, source = g.scene_case(seed), g.file_source(j)
                for f in range(g.frames):
                    out.append(FrameRef(len(out), s, g.kind, seed, f, g.frames, ids[s], case, source))
                s += 1
        return out

    def store_path(self, out: str | None = None) -> str:
        """Where the store goes: ``out`` (CLI) or ``self.out``, else ``$DENOISE_DATA/<name>.zarr``
        (``data/<name>.zarr`` when ``DENOISE_DATA`` is unset). A path ending in ``/`` or naming an
        existing folder without ``zarr.json`` gets ``<name>.zarr`` appended."""
        target = out or self.out
        if target is None:
            return str(Path(os.environ.get("DENOISE_DATA") or "data") / f"{self.name}.zarr")
        target = os.path.expandvars(os.path.expanduser(target))
        if "://" in target:
            return target
        p = Path(target)
        ours = (p / "zarr.json").exists() or (p / "dataset.lock").exists()     # a store, or one being made
        if target.endswith("/") or (p.is_dir() and not ours and p.suffix != ".zarr"):
            return str(p / f"{self.name}.zarr")
        return str(p)

    def with_overrides(self, **kw) -> "DatasetConfig":
        """A copy with top-level fields replaced (validated again)."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d.update(kw)
        return DatasetConfig(**d)

    def with_cluster(self, **kw) -> "DatasetConfig":
        c = {f.name: getattr(self.cluster, f.name) for f in fields(ClusterConfig)}
        c.update(kw)
        return self.with_overrides(cluster=ClusterConfig(**c))

    # -- (de)serialisation -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """Plain data (lists, dicts, scalars) that :meth:`from_dict` turns back into an equal config."""
        return {
            "name": self.name, "seed": int(self.seed), "out": self.out, "resolution": list(self.resolution),
            "scenes": [g.to_dict() for g in self.scenes],
            "render": _plain(self.render), "scene_gen": _plain(self.scene_gen), "store": _plain(self.store),
            "tasks": _plain({f.name: getattr(self.tasks, f.name) for f in fields(TaskConfig)}),
            "cluster": _plain({f.name: getattr(self.cluster, f.name) for f in fields(ClusterConfig)}),
            # only when set, so stores made before `split` existed still resume
            **({"split": _plain(self.split)} if self.split is not None else {}),
            # "scene_seed" (the scheme of stores made before `clip_ids` existed) is written as no key
            **({"clip_ids": self.clip_ids} if self.clip_ids != "scene_seed" else {}),
            **({"held_out": True} if self.held_out else {}),
        }

    def content_dict(self) -> dict:
        """What determines the dataset's bytes (no ``out``, ``cluster`` or ``tasks``): stored in the
        store's root attributes and compared on resume."""
        d = self.to_dict()
        for k in ("out", "cluster", "tasks"):
            d.pop(k)
        d["render"] = self.render_config().to_dict()
        d["render"].pop("threads", None)        # drjit's thread count does not change a byte
        d["store"] = {k: v for k, v in self.store_layout().to_dict().items() if k in STORE_KEYS}
        d["scene_gen"] = self.scene_gen_config().to_dict()
        return d

    @classmethod
    def from_dict(cls, d: Any) -> "DatasetConfig":
        d = known_keys(d, cls, "dataset", ConfigError)
        if "scenes" not in d:
            raise ConfigError("dataset.scenes is required: a list of {kind: indoor|outdoor, count: N, frames: F} "
                              "or {file: PATH, count: N, frames: F} groups")
        scenes = d["scenes"]
        need(isinstance(scenes, list) and len(scenes) > 0, "dataset.scenes",
             "a non-empty list of {kind, count, frames} groups", scenes, ConfigError)
        groups = []
        for i, g in enumerate(scenes):
            gd = known_keys(g, [*(f.name for f in fields(SceneGroup)), "sha256"], f"dataset.scenes[{i}]", ConfigError)
            gd.pop("sha256", None)                  # a file group's recorded hashes: content_dict has them anew
            for k in ("kind", "count") if gd.get("file") is None else ():
                if k not in gd:
                    raise ConfigError(f"dataset.scenes[{i}].{k} is required (or file: a Mitsuba scene file)")
            groups.append(SceneGroup(**gd))
        d["scenes"] = tuple(groups)
        d["tasks"] = TaskConfig(**known_keys(d.get("tasks"), TaskConfig, "dataset.tasks", ConfigError))
        cl = known_keys(d.get("cluster"), ClusterConfig, "dataset.cluster", ConfigError)
        if cl.get("jobqueue") is None:
            cl.pop("jobqueue", None)
        d["cluster"] = ClusterConfig(**cl)
        for k in ("render", "scene_gen", "store"):
            if d.get(k) is None:
                d[k] = {}
        if isinstance(d.get("resolution"), list):
            d["resolution"] = tuple(d["resolution"])
        return cls(**d)


def frame_bytes(cfg: DatasetConfig) -> int:
    """Bytes of one frame's arrays as the renderer hands them to the write task (float32): per-sample
    radiance + features (W·H·spp·20), sample layers, reference + stderr, guides (W·H·9)."""
    from stores.contract import NUM_FEATURES
    W, H = cfg.resolution
    rc = cfg.render_config()
    per_pixel = rc.spp * (3 + NUM_FEATURES) + 3 * rc.layer_levels + 6 + 9
    return 4 * W * H * per_pixel


def _gib(n: float) -> str:
    if n < 2 ** 20:
        return f"{n / 2 ** 10:.1f} KiB"
    return f"{n / 2 ** 30:.1f} GiB" if n >= 2 ** 28 else f"{n / 2 ** 20:.1f} MiB"


def worker_memory(cluster: ClusterConfig, *, workers: int | None = None) -> tuple[int | None, str]:
    """Memory one worker may use, in bytes, and where the figure comes from: ``memory_limit`` when
    given, the batch jobs' ``memory`` over their ``processes``, else (a LocalCluster) this machine's
    memory over its workers (``workers``, the CLI's ``--workers``, else ``cluster.workers``, else one
    per core). ``(None, ...)`` when it cannot be known here (an existing scheduler's workers: the
    CLI checks them once connected)."""
    from dask.utils import parse_bytes
    m = cluster.memory_limit
    if m not in (None, "auto", 0):
        try:
            v = int(m) if is_int(m, numpy=True) else int(parse_bytes(m))
            return v, f"cluster.memory_limit {m}"
        except (ValueError, TypeError):
            pass
    if cluster.kind in ("slurm", "pbs"):
        try:
            mem = int(parse_bytes(str(cluster.jobqueue.get("memory"))))
            # as pipeline.jobs.job_settings sets it: one worker a threads_per_worker cores by default
            procs = int(cluster.jobqueue.get("processes")
                        or max(1, int(cluster.jobqueue.get("cores") or 1) // cluster.threads_per_worker))
            where = f"cluster.jobqueue memory {cluster.jobqueue.get('memory')} over {procs} processes"
            return mem // max(1, procs), where
        except (ValueError, TypeError):
            return None, "unknown"
    if cluster.kind == "scheduler" or cluster.address:
        return None, "unknown until connected"
    try:
        import psutil
        total = int(psutil.virtual_memory().total)
    except ImportError:  # pragma: no cover - psutil comes with distributed
        return None, "unknown"
    cores = max(1, len(os.sched_getaffinity(0))) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    n = workers or cluster.workers or max(1, cores // cluster.threads_per_worker)
    return total // n, f"this machine's {total / 2 ** 30:.1f} GiB over {n} worker(s)"


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


def _unique_key_loader():
    """A yaml SafeLoader that refuses a mapping with the same key twice (PyYAML keeps the last)."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        pass

    def construct_mapping(loader, node, deep=False):
        # the node's own keys first: flattening splices in the keys of ``<<`` merges, which the
        # node's own keys override by design (``x: {<<: *base, a: 2}``)
        seen: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = loader.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                continue                                # yaml itself reports unhashable keys
            if key in seen:
                raise DuplicateKeyError(
                    f"duplicate key {key!r} (line {key_node.start_mark.line + 1}, first on line {seen[key] + 1})")
            seen[key] = key_node.start_mark.line
        loader.flatten_mapping(node)
        return yaml.SafeLoader.construct_mapping(loader, node, deep=deep)

    UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, construct_mapping)
    return UniqueKeyLoader


class DuplicateKeyError(ConfigError):
    """A YAML mapping gives the same key twice."""


def apply_overrides(data, overrides) -> dict:
    """``data`` (a config's YAML mapping) with each ``KEY=VALUE`` of ``overrides`` set: ``KEY`` a dotted
    path (``render.filter``, ``name``), ``VALUE`` read as YAML (``gaussian``, ``8``, ``[{file: DIR}]``)."""
    import yaml
    out = dict(data or {}) if isinstance(data, dict) else data
    for item in overrides or ():
        key, sep, text = str(item).partition("=")
        parts = key.strip().split(".")
        if not sep or not all(p.strip() for p in parts):
            raise ConfigError(f"--set {item!r} must be KEY=VALUE (KEY a dotted path such as render.filter)")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML: {e}") from None
        node = out
        for p in parts[:-1]:
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {p!r} is not a mapping in the config")
            node[p] = dict(node.get(p) or {})
            node = node[p]
        node[parts[-1]] = value
    return out


def load_config(path: str | os.PathLike, overrides=None) -> DatasetConfig:
    """Read and validate a YAML dataset config, with ``overrides`` (``KEY=VALUE`` strings,
    :func:`apply_overrides`) set; raises ConfigError naming the file and the field (a duplicate key, a
    directory or a missing file included)."""
    import yaml
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"config path {str(p)!r} is a directory, not a YAML file")
    if not p.exists():
        raise ConfigError(f"config file {str(p)!r} does not exist")
    try:
        data = yaml.load(p.read_text(), Loader=_unique_key_loader())
    except DuplicateKeyError as e:
        raise ConfigError(f"{p}: {e}") from e
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML: {e}") from e
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"config file {str(p)!r} cannot be read: {e}") from e
    if overrides:
        data = apply_overrides(data, overrides)
    try:
        return DatasetConfig.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from e
    except TypeError as e:      # e.g. a field given a mapping where a scalar belongs
        raise ConfigError(f"{p}: {e}") from e
