"""Pure task functions of the dataset graph (``pipeline.graph`` wires them; Dask runs them).

Every function is a pure function of plain data (a SceneSpec as JSON, a frame index, a render
config as a dict): its result depends on nothing else — not the worker, the retry or the clock (except
the ``*_seconds`` timings, which are metadata). A frame is rendered by one task
(:func:`render_whole_frame`, the default), or by three, one per stream, when ``tasks.split_streams``
says so (references on other workers; ``pipeline.render`` seeds every stream separately, so splitting
changes no byte):

- :func:`make_spec`        → SceneSpec JSON (str)
- :func:`render_inputs`    → per-sample inputs + guides + camera matrices (``pipeline.render.inputs_part``)
- :func:`render_layers`    → sample layers (``pipeline.render.layers_part``)
- :func:`render_reference` → reference mean + standard error (``pipeline.render.reference_part``)
- :func:`scene_spec`       → :func:`make_spec`, with the JSON stored once for the scene's clip (schema v3)
- :func:`write_frame`      → gathers the three parts (``pipeline.render.assemble``), writes the frame's
  image shards and returns a small summary with the frame's record, which the client commits
  (metadata, ``status/complete`` last: ``stores.writer``).

:func:`render_whole_frame` renders the same three parts on one loaded scene
(``pipeline.render.render_frame``).

Warm state per worker: the loaded scene of the last frame (:func:`frame_scene`) is kept, so the
three stream tasks of a frame that land on one worker one after another load and compile it once;
meshes are cached per process (``scene_gen.meshes``) and drjit caches compiled kernels on disk. Only
one scene is kept, and it is freed *before* the next one loads: drjit traces a virtual call (shape,
BSDF, emitter, texture) for every instance alive in the process, so each scene left alive grows every
later kernel (the Cornell box's path kernel: 1,281 operations alone, 26,659 beside one generated
scene) and LLVM's compile time with it. Keeping two scenes made train-cpu's run 1.65x as long
(628 against 379 s; 6-12 s of compile a frame, where the render itself took 6-15 s;
docs/throughput.md). With several threads a worker, scenes in use by other tasks stay alive beside a
new one: one scene alive holds for one thread a worker (the default). Each rendering task sizes
drjit's thread pool to its Dask worker's thread count, so workers do not oversubscribe the cores.
"""
from __future__ import annotations

import dataclasses
import gc
import hashlib
import json
import sys
import threading
import time
import weakref
from collections import OrderedDict

SCENE_CACHE_SIZE = 1          # loaded scenes kept per worker process (a frame's three streams)
_scenes: OrderedDict = OrderedDict()
_loaded = weakref.WeakSet()   # every FrameScene this process loaded and that is still alive
_in_flight = weakref.WeakSet()   # the ones running tasks hold right now (not to be freed)
_scenes_lock = threading.Lock()
_in_use = 0                   # scenes taken out of the cache by running tasks


def worker_threads() -> int | None:
    """Threads of the Dask worker running this task (None outside a worker)."""
    try:
        from distributed import get_worker
        return int(get_worker().state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None


def _render_cfg(render: dict):
    from pipeline.render import RenderConfig
    cfg = RenderConfig.from_dict(dict(render))
    n = worker_threads()
    if n:
        cfg = dataclasses.replace(cfg, threads=n)
    return cfg


class frame_scene:
    """``with frame_scene(spec_json, frame, render) as fs``: a ``pipeline.render.FrameScene``, taken from
    this process's cache when the same (spec, frame, config) was loaded before, else loaded.

    A scene is used by one task at a time (taken out of the cache while in use, put back after), so
    tasks in several threads never share one; ``fs.load_seconds`` is 0 for a cached scene. Before a
    scene loads, the cached ones are freed (see the module's note), and when no other task holds a
    scene, drjit's in-memory kernels too (they stay in drjit's disk cache), so kernels do not pile up
    in a long-running worker.
    """

    def __init__(self, spec_json: str, frame: int, render: dict):
        cfg = _render_cfg(render)
        self.key = (hashlib.sha1(spec_json.encode()).hexdigest(), int(frame),
                    json.dumps(cfg.to_dict(), sort_keys=True))
        self.spec_json, self.frame, self.cfg = spec_json, int(frame), cfg

    def __enter__(self):
        global _in_use
        with _scenes_lock:
            fs = _scenes.pop(self.key, None)
            _in_use += 1
            if fs is None:                  # free the cached scene first (tasks entering wait for that)
                _evict_locked(flush_kernels=_in_use == 1)
        if fs is None:
            from pipeline.render import FrameScene
            t0 = time.perf_counter()
            try:
                fs = FrameScene(parsed_spec(self.spec_json, self.key[0]), self.frame, self.cfg)
            except BaseException:
                self._release()
                raise
            fs.load_seconds = time.perf_counter() - t0
            _loaded.add(fs)
        else:
            fs.load_seconds = 0.0
        _in_flight.add(fs)
        self.fs = fs
        return fs

    @staticmethod
    def _release() -> None:
        global _in_use
        with _scenes_lock:
            _in_use -= 1

    def __exit__(self, exc_type, exc, tb):
        global _in_use
        fs, self.fs = self.fs, None
        _in_flight.discard(fs)
        if exc_type is not None:
            self._release()
            return False                    # a scene that failed mid-render is not reused
        try:
            fs.set_time(0.0)
        except BaseException:
            self._release()
            raise
        with _scenes_lock:                  # released and cached at once: no load can slip in between
            _in_use -= 1
            _scenes[self.key] = fs
            _scenes.move_to_end(self.key)
            while len(_scenes) > SCENE_CACHE_SIZE:
                _scenes.popitem(last=False)
        return False


_specs: OrderedDict = OrderedDict()      # sha1 of a SceneSpec JSON -> the parsed SceneSpec (a few)


def parsed_spec(spec_json: str, digest: str):
    """``SceneSpec.from_json(spec_json)``, parsed once per process for the frames of a clip: a clip's
    JSON holds a camera a frame, so parsing it for every frame would cost in proportion to the clip's
    length (a 5,000-frame clip's ~1 MB: ~0.1 s a frame). SceneSpecs are frozen, so sharing is safe."""
    from scene_gen.spec import SceneSpec
    with _scenes_lock:
        spec = _specs.get(digest)
        if spec is not None:
            _specs.move_to_end(digest)
            return spec
    spec = SceneSpec.from_json(spec_json)
    with _scenes_lock:
        _specs[digest] = spec
        while len(_specs) > 4:
            _specs.popitem(last=False)
    return spec


def _evict_locked(*, flush_kernels: bool) -> None:
    _scenes.clear()
    # A scene in a reference cycle (or a failed task's, held by its traceback) would stay registered
    # with drjit: collect cycles, but only when a scene outlived the clear (a full collection costs
    # ~90 ms in a worker's large heap, more than rendering an 8x8 frame; most scenes go by refcount).
    if any(True for fs in _loaded if fs not in _in_flight):
        gc.collect()
    if flush_kernels and "drjit" in sys.modules:
        sys.modules["drjit"].flush_kernel_cache()


def clear_scene_cache(*, flush_kernels: bool = False) -> None:
    """Free the cached scenes (and with ``flush_kernels``, drjit's in-memory kernels, when no task in
    this process holds a scene)."""
    with _scenes_lock:
        _evict_locked(flush_kernels=flush_kernels and _in_use == 0)


def make_spec(seed: int, kind: str, num_frames: int, res: tuple[int, int], scene_gen: dict, case: str = "") -> str:
    """The SceneSpec JSON of one scene (``scene_gen.sampling.sample_scene``; ``res`` = (W, H)), with the
    hard cases ``case`` applied (``scene_gen.cases``: their settings, then their edits). A scene file's
    (``kind`` ``file``): ``scene_gen`` is its source (``pipeline.groups.SceneGroup.file_source``: the file,
    its content hash and the camera settings), and its cameras are drawn around the file's sensor
    (``scene_gen.scene_files``: the file is loaded once here to learn the sensor)."""
    from scene_gen import scene_files
    if kind == scene_files.KIND:
        settings = scene_files.CameraSettings.from_dict(scene_gen.get("camera"))
        info = scene_files.inspect(scene_gen["path"], settings)
        return scene_files.file_spec(scene_gen["path"], scene_gen["sha256"], info, settings, int(seed),
                                     int(num_frames)).to_json()
    from scene_gen.cases import apply_cases, case_config
    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    cfg = SceneGenConfig.from_dict(dict(scene_gen))
    spec = sample_scene(int(seed), kind, num_frames=int(num_frames), res=int(max(res)),
                        config=case_config(cfg, case) if case else cfg)
    return (apply_cases(spec, case, int(max(res))) if case else spec).to_json()


def _part(fn, spec_json: str, frame: int, render: dict) -> dict:
    with frame_scene(spec_json, frame, render) as fs:
        out = fn(fs)
        out["seconds"] += fs.load_seconds
        out["load_seconds"] = fs.load_seconds      # for the run's time line (not stored)
    return out


def render_inputs(spec_json: str, frame: int, render: dict) -> dict:
    """Per-sample inputs of one frame (``pipeline.render.inputs_part``)."""
    from pipeline.render import inputs_part
    return _part(inputs_part, spec_json, frame, render)


def render_layers(spec_json: str, frame: int, render: dict) -> dict:
    """Sample layers of one frame (``pipeline.render.layers_part``)."""
    from pipeline.render import layers_part
    return _part(layers_part, spec_json, frame, render)


def render_reference(spec_json: str, frame: int, render: dict) -> dict:
    """Reference of one frame (``pipeline.render.reference_part``)."""
    from pipeline.render import reference_part
    return _part(reference_part, spec_json, frame, render)


def render_whole_frame(spec_json: str, frame: int, render: dict) -> dict:
    """The whole frame in one task (``pipeline.render.render_loaded``): the ``stores.contract`` dict."""
    from pipeline.render import render_loaded
    with frame_scene(spec_json, frame, render) as fs:
        out = render_loaded(fs, spec_json)
        out["meta"]["render_seconds"] += fs.load_seconds
        out["load_seconds"] = fs.load_seconds      # for the run's time line (not stored)
    del out["meta"]["scene_json"]       # the write task has it (its spec argument): not sent along a frame
    return out


def assemble(spec_json: str, frame: int, inputs: dict, layers: dict, reference: dict) -> dict:
    """The ``stores.contract`` frame dict from the three parts (``pipeline.render.assemble``)."""
    from pipeline.render import assemble as _assemble
    return _assemble(spec_json, frame, inputs, layers, reference)


_writers: OrderedDict = OrderedDict()      # (store, generation) -> StoreWriter, a few per process
_writers_lock = threading.Lock()


def store_writer(store: str, generation: str = ""):
    """This process's :class:`stores.writer.StoreWriter` of ``store``, opened once per ``generation``
    (the client's :func:`stores.writer.generation` of the store: its id and frame count), not once per
    frame: opening checks every array's metadata (tens of milliseconds), more than an 8x8 frame's write."""
    from stores.writer import StoreWriter
    key = (str(store), str(generation))
    with _writers_lock:
        w = _writers.get(key) if generation else None
        if w is None:
            w = StoreWriter(store)
            if generation:
                _writers[key] = w
                while len(_writers) > 4:
                    _writers.popitem(last=False)
        return w


def scene_spec(store: str, first: int, seed: int, kind: str, num_frames: int, res: tuple[int, int],
               scene_gen: dict, case: str = "", *, generation: str = "", make=None) -> str:
    """:func:`make_spec` (or ``make``, the same signature), and the SceneSpec JSON stored once for the
    scene's clip, at its first frame ``first`` (``frames/scene_json``), before any of its
    frames is written: every frame task depends on this one. The same bytes on every run, so a resume
    rewriting it changes nothing."""
    spec_json = (make or make_spec)(seed, kind, num_frames, res, scene_gen, *((case,) if case else ()))
    store_writer(store, generation).write_scene_json(int(first), spec_json)
    return spec_json


def write_frame(store: str, index: int, spec_json: str, frame: int, *parts: dict, clip_id: int | None = None,
                generation: str = "") -> dict:
    """Write frame ``index``'s data from one whole-frame dict or the three parts (inputs, layers,
    reference): its image shards (``StoreWriter.write_frame_data``). ``clip_id`` (the scene's, from
    ``pipeline.config``; default: the scene seed) goes into its record and decides the split. Returns a
    summary (index, frame, scene seed, render and write seconds, reference spp and relative standard
    error, non-finite counts, ``checked``: the frame's value problems, ``stores.fitness.check_values``
    of what was written) with the frame's ``record``, which the client commits (``StoreWriter.commit``:
    metadata, then ``status/complete``)."""
    from stores.fitness import check_values
    load_s = sum(float(p.get("load_seconds", 0.0)) for p in parts)
    parts = tuple({k: v for k, v in p.items() if k != "load_seconds"} for p in parts)
    if len(parts) == 1:
        arrays = {**parts[0], "meta": {"scene_json": spec_json, **parts[0]["meta"]}}
    elif len(parts) == 3:
        arrays = assemble(spec_json, frame, *parts)
    else:
        raise TypeError(f"write_frame takes one whole frame or three parts, got {len(parts)}")
    if clip_id is not None:
        arrays = {**arrays, "meta": {**arrays["meta"], "clip_id": int(clip_id)}}
    t0 = time.perf_counter()
    w = store_writer(store, generation)
    record = w.write_frame_data(int(index), arrays)
    write_s = time.perf_counter() - t0
    meta = arrays["meta"]
    problems = check_values({k: v for k, v in arrays.items() if k != "meta"}, w.layout).problems
    return {"index": int(index), "frame": int(frame), "scene_seed": int(meta["scene_seed"]),
            "render_seconds": float(meta["render_seconds"]), "write_seconds": write_s, "load_seconds": load_s,
            "reference_spp": int(meta["reference_spp"]), "reference_rel_stderr": float(meta["reference_rel_stderr"]),
            "nonfinite": int(meta["nonfinite_inputs"] + meta["nonfinite_layers"] + meta["nonfinite_reference"]),
            "checked": problems, "record": record, "done_at": time.time()}
