"""Renderer benchmark (``python -m pipeline bench --only render``): figures, not a timed test.

Printed in one run, every speed a ratio of two rates measured back to back in this process (or, for
the dataset, in the same run), since the machine may be shared:

- **input loop vs mi.render** on one generated scene (``configs/default.yaml``'s scene generator,
  loaded as the renderer loads it: merged shapes): samples/s of ``pipeline.render.render_inputs``
  (radiance + 17 features) against plain ``mi.render`` of the same scene and spp (target >= 0.9);
- **reference vs mi.render**: ``render_reference`` (passes of the production size, 128 spp, plus the
  batch-means standard error) against one ``mi.render`` call of the same total spp (target >= 0.9);
- **generated scene vs the Cornell box** (``mi.cornell_box()``, same resolution, bounces and spp):
  ``mi.render`` on the generated scene as the renderer loads it, and as it was loaded before shapes
  were merged (one shape a mesh, no material palette), each against the Cornell box (content: what a
  sample of our scenes costs, not a target).
  Each scene is loaded, timed and freed in turn, alone in the process: drjit traces a virtual call for
  every instance alive, so a scene timed beside another is slower (the Cornell box by a third beside
  one generated scene; figures before this rule flattered the generated scenes);
- **end-to-end dataset samples/s vs plain mi.render** (the throughput measure, issue 57): ``python -m
  pipeline dataset`` on eight frames (two indoor and two outdoor stills, and a 4-frame indoor clip whose
  camera and objects move; default scene generator) at 128x128 and at 256x256 on a LocalCluster of
  ``e2e_workers`` workers, caches warm (a first run at 128x128 fills them), all samples (inputs, layers,
  the references' samples as taken) over the wall time, start-up and validation included, against plain
  ``mi.render`` of the same frames and samples (each frame's scene loaded as the renderer loads it, its
  samples in one call on as many drjit threads; :func:`plain_render`); also per CPU-second, the figure to
  read when other work shares the machine, and the share of the cores' time the run left idle. The Cornell box at the
  same size is printed beside it as content, not a target: a generated sample is dearer (see
  docs/throughput.md);
- **frames per hour at 256x256** for the default scene mix: ``pipeline.estimate.calibrate`` of the
  first indoor and outdoor scene of ``configs/default.yaml`` at 256x256 (one thread a worker, as many
  side by side as this machine has workers; the references' early stop predicted), their frame times
  weighted by the mix's frames of each kind, for one worker and for this machine's workers;
- **launches**: drjit kernel launches and device-to-host reads of the input loop against ``mi.render``
  of the same samples (kernel history, deterministic on LLVM; :func:`launch_counts`), one 64x64 frame
  at 8 spp of a scene with moving objects, static (shutter closed) and moving (time slices);
- peak resident memory of a child process that renders one whole 256x256x8 frame (inputs, layers,
  a small reference) with ``render_frame`` (target < 4 GiB).

Throughput of the loops is measured at ``res`` (default 128x128: the ratios do not depend on it) as
the best of ``repeats`` alternating runs of ours and ``mi.render``.
"""
from __future__ import annotations

import dataclasses
import json
import math
from functools import partial
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.estimate import scratch_dir

TARGET_INPUT_RATIO = 0.9
TARGET_REFERENCE_RATIO = 0.9
TARGET_PEAK_GIB = 4.0
ROOT = Path(__file__).resolve().parent.parent
DEFAULT_CONFIG = ROOT / "configs" / "default.yaml"

_CHILD = r"""
import json, resource, sys, time
from pipeline.render import RenderConfig, render_frame
from scene_gen.sampling import sample_scene
seed, kind, res, spp = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
spec = sample_scene(seed, kind, num_frames=1, res=res)
t = time.perf_counter()
out = render_frame(spec, 0, RenderConfig(res=(res, res), spp=spp, ref_spp=64, ref_passes=16))
print(json.dumps({"seconds": time.perf_counter() - t,
                  "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                  "radiance_bytes": int(out["radiance"].nbytes + out["features"].nbytes)}))
"""



def _best_pair(fa, fb, repeats: int) -> tuple[float, float]:
    """Best wall time of ``fa`` and of ``fb``, run alternately so load changes hit both alike."""
    ta = tb = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fa()
        ta = min(ta, time.perf_counter() - t)
        t = time.perf_counter()
        fb()
        tb = min(tb, time.perf_counter() - t)
    return ta, tb


def _cornell(mi, res: int, max_depth: int):
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=res, height=res, rfilter={"type": "box"})
    d["integrator"] = {"type": "path", "max_depth": max_depth + 1, "rr_depth": max_depth + 2}
    return mi.load_dict(d)


def _collect() -> None:
    import gc
    gc.collect()


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


LAUNCH_KINDS = ("JIT", "BlockReduce", "Reduce", "CallReduce")     # kernels that compute (memsets, copies apart)


def launches(dr, fn) -> dict:
    """drjit's kernel history (LLVM: deterministic) over ``fn()``: ``kernels`` (JIT kernels and block
    reductions, the launches that compute), ``jit`` (JIT kernels alone), ``other`` (memsets, copies,
    uploads and the like) and ``by_type``."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        fn()
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    by = {}
    for k in hist:
        t = str(k["type"]).rsplit(".", 1)[-1]
        by[t] = by.get(t, 0) + 1
    kernels = sum(by.get(t, 0) for t in LAUNCH_KINDS)
    return {"kernels": kernels, "jit": by.get("JIT", 0), "other": sum(by.values()) - kernels, "by_type": by}


def kernel_counts(*, seed: int = 0, kind: str = "indoor", res: int = 64, spp: int = 8,
                  scene_gen: dict | None = None) -> dict:
    """:func:`launch_counts` of one generated scene with moving objects (``p_motion`` 1) at ``res``."""
    from pipeline import render as R
    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    gen = SceneGenConfig.from_dict({**(scene_gen or {}), "p_motion": 1.0})
    spec = sample_scene(seed, kind, num_frames=1, res=res, config=gen)
    return launch_counts(spec, R.RenderConfig(res=(res, res), spp=spp, ref_spp=0, layer_levels=0))


def launch_counts(spec, cfg) -> dict:
    """Launches and device-to-host reads of the input loop (``pipeline.render.inputs_part``) against
    ``mi.render`` of the same samples, frame 0 of ``spec``: ``static`` (the scene with its shutter closed)
    and, where objects move, ``moving`` (``mi.render`` at the same slice times as
    ``pipeline.render.render_sliced``; ``set_time``: what moving the objects costs a slice, and each
    side's kernels without it). Reads are counted at the input loop's one read function
    (``pipeline.render.inputs._read``) and at ``mi.render``'s image (one a call). One scene alive at a time."""
    import dataclasses
    from pipeline import render as R
    out = {}
    for name, sp in (("static", dataclasses.replace(spec, shutter=0.0)), ("moving", spec)):
        if name == "moving" and not spec.has_motion:
            continue
        fs = R.FrameScene(sp, 0, cfg)
        out[name] = _frame_counts(R, fs)
        del fs
        _collect()
    return out


def _frame_counts(R, fs) -> dict:
    from pipeline.render import inputs as I
    dr, spp = fs.dr, fs.cfg.spp
    reads, read = [0], I._read

    def counted(buf):
        reads[0] += 1
        return read(buf)

    R.inputs_part(fs)                           # compile (or load) the kernels first; counts are the same
    I._read = counted
    try:
        ours = launches(dr, lambda: R.inputs_part(fs))
    finally:
        I._read = read
    ours.update(reads=reads[0], wavefronts=len(list(I._input_wavefronts(fs))))
    theirs = launches(dr, lambda: R.render_sliced(fs, spp, R.STREAM_ORACLE, 0, max_slices=fs.cfg.time_slices))
    g = math.gcd(fs.cfg.time_slices, spp) if fs.has_motion else 1
    theirs["reads"] = g
    out = {"input_loop": ours, "mi_render": theirs}
    if fs.has_motion:                           # each moves the objects once a slice; inputs_part also back to rest
        fs.set_time(0.0)
        st = out["set_time"] = launches(dr, lambda: fs.set_time(0.5))
        ours["own_kernels"] = ours["kernels"] - (g + 1) * st["kernels"]
        theirs["own_kernels"] = theirs["kernels"] - g * st["kernels"]
        out["moving_objects"] = len(fs.loaded.moving)
    return out


def _launches_section(*, seed: int, kind: str, res: int, scene_gen: dict) -> dict:
    counts = kernel_counts(seed=seed, kind=kind, res=res, spp=8, scene_gen=scene_gen)
    print(f"  launches of one {res}x{res} frame at 8 spp (drjit kernel history; {kind} seed {seed} with moving "
          "objects):", flush=True)
    _print_counts(counts)
    return counts


def _print_counts(c: dict) -> None:
    for name, d in c.items():
        a, b = d["input_loop"], d["mi_render"]
        print(f"  {name:7s} input loop {a['kernels']} kernels ({a['jit']} JIT) + {a['other']} other launches, "
              f"{a['reads']} read-back(s), {a['wavefronts']} wavefront(s); mi.render of the same samples "
              f"{b['kernels']} kernels ({b['jit']} JIT) + {b['other']} other, {b['reads']} read-back(s)", flush=True)
        if "set_time" in d:
            st = d["set_time"]
            print(f"          set_time (moving {d['moving_objects']} object(s)) costs {st['kernels']} kernels "
                  f"({st['jit']} JIT) + {st['other']} other a slice; without it: input loop {a['own_kernels']} "
                  f"kernels, mi.render {b['own_kernels']}", flush=True)


# The throughput measure's frames (issue 57): four stills and one 4-frame clip whose camera and objects move
# (at the bench's seed, 4243, 19 of its 52 objects move).
E2E_SCENES = ({"kind": "indoor", "count": 2}, {"kind": "outdoor", "count": 2},
              {"kind": "indoor", "count": 1, "frames": 4})
E2E_SIZES = (128, 256)             # where users render; at 64x64 the run's fixed costs are most of it


def end_to_end(*, res: int, ref_spp: int, workers: int, scene_gen: dict, render: dict | None = None,
               scenes=E2E_SCENES, seed: int = 4243) -> dict:
    """Wall and CPU time of ``python -m pipeline dataset`` on ``scenes`` (a child process, warm caches: run
    once first where they may be cold) against plain ``mi.render`` of the same frames and samples
    (:func:`plain_render`: each frame's inputs, layers and the reference samples it took). ``render``:
    settings over the bench's. Also the share of the cores' time the run left idle."""
    import yaml

    from stores.reader import open_store
    passes = 32 if ref_spp >= 32 * 16 else 8
    rc = {"spp": 8, "layer_levels": 6, "ref_spp": ref_spp, "ref_passes": passes, "ref_min_passes": passes // 2,
          **(render or {})}
    cfg = {"name": "bench-e2e", "seed": seed, "resolution": [res, res], "scenes": [dict(g) for g in scenes],
           "render": rc, "scene_gen": scene_gen, "tasks": {"retries": 0},
           "cluster": {"kind": "local", "workers": workers, "threads_per_worker": 1, "dashboard_address": None}}
    with tempfile.TemporaryDirectory(prefix="bench-e2e-", dir=scratch_dir()) as tmp:
        path = Path(tmp) / "e2e.yaml"
        path.write_text(yaml.safe_dump(cfg))
        import resource
        c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        r = subprocess.run([sys.executable, "-m", "pipeline", "dataset", "--config", str(path),
                            "--out", str(Path(tmp) / "e2e.zarr"), "--workers", str(workers)],
                           capture_output=True, text=True, env=_env(), cwd=ROOT)
        wall = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)   # the run and its worker processes
        if r.returncode != 0:
            raise RuntimeError("the end-to-end dataset run failed: "
                               + "\n".join((r.stdout + r.stderr).strip().splitlines()[-8:]))
        store = open_store(Path(tmp) / "e2e.zarr")
        layers = sum(2 ** n for n in range(rc["layer_levels"]))        # 1 + 2 + ... + 32 = 63
        spp = [int(rc["spp"] + layers + s) for s in store.meta_column("reference_spp")]
        moving = int(np.sum(store.meta_column("has_motion")))
        samples = res * res * sum(spp)
        plain = plain_render(Path(tmp) / "e2e.zarr", spp=spp, threads=workers,
                             cfg=dict(res=(res, res), spp=8, layer_levels=6, ref_spp=ref_spp, ref_passes=passes,
                                      ref_min_passes=passes // 2))
    return {"res": res, "frames": len(spp), "moving_frames": moving, "wall_s": wall, "cpu_s": cpu,
            "samples": samples, "msamples_per_s": samples / wall / 1e6, "msamples_per_cpu_s": samples / cpu / 1e6,
            "idle_core_share": max(0.0, 1.0 - cpu / (wall * workers)), "plain_wall_s": plain["wall_s"],
            "plain_cpu_s": plain["cpu_s"], "plain_msamples_per_s": samples / plain["wall_s"] / 1e6,
            "plain_msamples_per_cpu_s": samples / plain["cpu_s"] / 1e6,
            "ratio": plain["wall_s"] / wall, "ratio_per_cpu_s": plain["cpu_s"] / cpu}


def plain_render(store_path, *, spp, threads: int, cfg: dict) -> dict:
    """The same frames and samples with plain ``mi.render``, the measure of the pipeline's throughput:
    each frame of the store (its own frame of its clip) at its ``spp`` (a list, a frame each: all its
    inputs, layers and reference samples; or one count for all) in one call on ``threads`` drjit threads,
    its scene loaded as the renderer loads it (scene loading and kernel compilation timed, as the dataset
    run's are), one scene alive at a time. Wall and CPU seconds."""
    from pipeline import render as R
    from scene_gen.spec import SceneSpec
    from stores.reader import open_store
    store = open_store(store_path)
    frames = store.meta_column("frame")
    jobs = [(SceneSpec.from_json(store.scene_json(i)), int(frames[i]),
             int(spp[i]) if hasattr(spp, "__len__") else int(spp)) for i in range(store.num_frames)]
    rc = R.RenderConfig(**cfg)
    import drjit as dr                  # the process's renderer is loaded (run() timed it first)
    before = int(dr.thread_count())
    dr.set_thread_count(threads)
    try:
        t, c = time.perf_counter(), time.process_time()
        for spec, frame, n in jobs:
            fs = R.FrameScene(spec, frame, rc)
            np.asarray(fs.mi.render(fs.scene, spp=n, seed=1))
            del fs
            _collect()
        return {"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c}
    finally:
        dr.set_thread_count(before)


def frames_per_hour(*, res: int, workers: int, scene_gen: dict | None = None) -> dict:
    """Frames per hour at ``res`` for the default config's scene mix (``pipeline.estimate.calibrate``)."""
    from pipeline.config import SceneGroup, load_config
    from pipeline.estimate import calibrate, local_slots
    from scene_gen.families import family_names
    d = load_config(DEFAULT_CONFIG)
    kinds = [k for k in family_names() if any(g.kind == k for g in d.scenes)]
    mix = {k: sum(g.count * g.frames for g in d.scenes if g.kind == k) for k in kinds}
    # the first scene of each kind keeps its seed: groups in the default order, one scene each
    cal_cfg = d.with_overrides(resolution=(res, res), scene_gen={**d.scene_gen, **(scene_gen or {})},
                               scenes=tuple(SceneGroup(k, 1) for k in kinds))
    # the workers render side by side, as in a run (they slow each other down)
    cal = calibrate(cal_cfg, per_group=1, threads=1, concurrent=min(workers, local_slots(1)), log=lambda *a: None)
    t = {f["kind"]: f["frame_s"] for f in cal["frames"]}
    mean_s = sum(mix[k] * t[k] for k in mix) / sum(mix.values())
    return {"frame_s": t, "mean_frame_s": mean_s, "frames_per_hour_per_worker": 3600.0 / mean_s,
            "frames_per_hour": 3600.0 / mean_s * workers, "workers": workers}


def _mi_render(mi, scene, spp: int) -> None:
    """Plain ``mi.render`` of ``scene`` at ``spp``, its image read back (the timed call of every comparison)."""
    np.asarray(mi.render(scene, spp=spp, seed=12345))


def _bench_scenes(*, seed: int, kind: str, res: int, spp: int, ref_passes: int, ref_spp: int, scene_gen: dict):
    """The scene :func:`run` times (shutter closed), the render config (the reference with its
    production pass size) and the same scene as it was loaded before shapes were merged (no material
    palette, shutter closed)."""
    from pipeline import render as R
    from scene_gen.config import SceneGenConfig
    from scene_gen.sampling import sample_scene
    spec = sample_scene(seed, kind, num_frames=1, res=res, config=SceneGenConfig.from_dict(scene_gen))
    # the benchmark measures one static pass: motion slicing is a scene property, not loop speed
    spec = dataclasses.replace(spec, shutter=0.0) if spec.has_motion else spec
    # the reference with its production pass size (4096 spp in 32 passes = 128 spp a pass), fewer passes
    cfg = R.RenderConfig(res=(res, res), spp=spp, ref_spp=ref_spp, ref_passes=ref_passes,
                         ref_min_passes=min(16, ref_passes), layer_levels=0)
    before_gen = SceneGenConfig.from_dict({k: v for k, v in scene_gen.items() if k != "material_palette"})
    before_spec = dataclasses.replace(sample_scene(seed, kind, num_frames=1, res=res, config=before_gen), shutter=0.0)
    return spec, cfg, before_spec


def _loop_times(spec, cfg, *, spp: int, ref_spp: int, ref_pass_spp: int, repeats: int):
    """The input loop and the reference against ``mi.render`` on ``spec``, best of alternating runs after
    a warm-up: ``(mi, dr, times)``, times the seconds of each (``t_in``, ``t_mi``, ``t_ref``,
    ``t_mi_ref``) and of the warm-up (``warm``), drjit's ``threads`` and the scene's ``shapes``."""
    from pipeline import render as R
    t0 = time.perf_counter()
    fs = R.FrameScene(spec, 0, cfg)
    mi, dr = fs.mi, fs.dr
    threads = int(dr.thread_count())
    shapes = len(fs.scene.shapes())
    R.render_inputs(fs)            # warm-up: compile the kernels once
    _mi_render(mi, fs.scene, spp)
    _mi_render(mi, fs.scene, ref_pass_spp)
    warm = time.perf_counter() - t0
    scene = fs.scene
    t_in, t_mi = _best_pair(partial(R.render_inputs, fs), partial(_mi_render, mi, scene, spp),
                            3 * repeats)  # short calls
    t_ref, t_mi_ref = _best_pair(partial(R.render_reference, fs), partial(_mi_render, mi, scene, ref_spp),
                                 max(1, repeats - 1))
    fs = scene = None               # the scene freed before the next loads (one alive at a time)
    _collect()
    return mi, dr, {"threads": threads, "shapes": shapes, "warm": warm, "t_in": t_in, "t_mi": t_mi,
                    "t_ref": t_ref, "t_mi_ref": t_mi_ref}


def _isolated(mi, load, spp: int) -> tuple[float, int]:
    """Best time of ``spp`` samples a pixel on the scene ``load()`` returns, alone in the process
    (and its shape count)."""
    scene = load()
    _mi_render(mi, scene, spp)                # kernels: compiled, or from drjit's cache
    t = float("inf")
    for _ in range(2):
        t1 = time.perf_counter()
        _mi_render(mi, scene, spp)
        t = min(t, time.perf_counter() - t1)
    n = len(scene.shapes())
    del scene
    _collect()
    return t, n


def _scene_times(mi, spec, cfg, before_spec, *, res: int, spp: int, repeats: int) -> dict:
    """Best seconds of ``spp`` samples a pixel on the generated scene (``t_gen``), the Cornell box
    (``t_cb``) and the generated scene before merging (``t_before``), each alone in the process, in
    turn; and the shapes before merging (``before_shapes``)."""
    from pipeline import render as R
    t_gen = t_cb = t_before = float("inf")
    before_shapes = 0
    for _ in range(max(1, repeats)):
        t_gen = min(t_gen, _isolated(mi, lambda: R.FrameScene(spec, 0, cfg).scene, spp)[0])
        t_cb = min(t_cb, _isolated(mi, lambda: _cornell(mi, res, spec.max_depth), spp)[0])
        t, before_shapes = _isolated(mi, lambda: R.FrameScene(before_spec, 0, cfg, merge=False).scene, spp)
        t_before = min(t_before, t)
    return {"t_gen": t_gen, "t_cb": t_cb, "t_before": t_before, "before_shapes": before_shapes}


def _loop_figures(t: dict, *, scene: str, n_in: int, n_ref: int, n_cb: int) -> dict:
    """:func:`run`'s first figures, printed: the times ``t`` of :func:`_loop_times` and :func:`_scene_times`
    as rates and ratios; ``n_*``: the samples of each timed call."""
    out = {
        "scene": scene,
        "threads": t["threads"],
        "warmup_seconds": t["warm"],
        "inputs_msamples_per_s": n_in / t["t_in"] / 1e6,
        "mi_render_msamples_per_s": n_in / t["t_mi"] / 1e6,
        "inputs_ratio": t["t_mi"] / t["t_in"],
        "reference_msamples_per_s": n_ref / t["t_ref"] / 1e6,
        "mi_render_reference_msamples_per_s": n_ref / t["t_mi_ref"] / 1e6,
        "reference_ratio": t["t_mi_ref"] / t["t_ref"],
        "cornell_msamples_per_s": n_cb / t["t_cb"] / 1e6,
        "generated_msamples_per_s": n_cb / t["t_gen"] / 1e6,
        "generated_vs_cornell": t["t_cb"] / t["t_gen"],
        "generated_before_merge_msamples_per_s": n_cb / t["t_before"] / 1e6,
        "generated_before_merge_vs_cornell": t["t_cb"] / t["t_before"],
    }
    print(f"renderer on {out['scene']} ({t['threads']} threads, warm-up {t['warm']:.1f} s):", flush=True)
    print(f"  input loop  {out['inputs_msamples_per_s']:.2f} Msamples/s vs mi.render "
          f"{out['mi_render_msamples_per_s']:.2f}: ratio {out['inputs_ratio']:.2f} (target >= {TARGET_INPUT_RATIO})")
    print(f"  reference   {out['reference_msamples_per_s']:.2f} Msamples/s vs mi.render "
          f"{out['mi_render_reference_msamples_per_s']:.2f}: ratio {out['reference_ratio']:.2f} "
          f"(target >= {TARGET_REFERENCE_RATIO})")
    print(f"  generated   {out['generated_msamples_per_s']:.2f} Msamples/s vs Cornell box "
          f"{out['cornell_msamples_per_s']:.2f}: ratio {out['generated_vs_cornell']:.2f} "
          f"(content, not a target; before merging {out['generated_before_merge_vs_cornell']:.2f})",
          flush=True)
    return out


def _cornell_rates(mi, dr, *, res: int, max_depth: int, workers: int, threads: int) -> tuple[float, float]:
    """Msamples/s and Msamples a CPU-second of ``mi.render`` on the Cornell box at ``res`` (1024 spp
    after a 64-spp warm-up) on ``workers`` drjit threads (``threads`` restored after), alone in this
    process."""
    cb = _cornell(mi, res, max_depth)          # alone in this process (see run)
    dr.set_thread_count(workers)
    _mi_render(mi, cb, 64)
    t, c = time.perf_counter(), time.process_time()
    _mi_render(mi, cb, 1024)
    n = res * res * 1024
    cb_rate, cb_cpu_rate = n / (time.perf_counter() - t) / 1e6, n / (time.process_time() - c) / 1e6
    dr.set_thread_count(threads)
    del cb
    _collect()
    return cb_rate, cb_cpu_rate


def _dataset_section(mi, dr, *, sizes, ref_spp: int, workers: int, threads: int, scene_gen: dict,
                     max_depth: int, warm: bool = True) -> dict:
    """The throughput measure at each of ``sizes``: the end-to-end dataset run (:func:`end_to_end`, after a
    run of the same frames with 64-spp references so that caches are warm: some kernels depend on the
    film's size) against plain ``mi.render`` of its frames, and against the Cornell box at the first
    size, with as many threads as its workers: figures, printed."""
    out, runs = {}, {}
    for res in sizes:
        if warm:        # the same scenes at this size: their kernels in drjit's disk cache, meshes cached
            end_to_end(res=res, ref_spp=min(ref_spp, 64), workers=workers, scene_gen=scene_gen)
        e2e = runs[res] = end_to_end(res=res, ref_spp=ref_spp, workers=workers, scene_gen=scene_gen)
        out.update({f"dataset_vs_mi_render_{res}": e2e["ratio"],
                    f"dataset_vs_mi_render_per_cpu_s_{res}": e2e["ratio_per_cpu_s"],
                    f"dataset_idle_core_share_{res}": e2e["idle_core_share"]})
        print(f"  dataset {res}x{res}: {e2e['frames']} frames ({e2e['frames'] - 4} of a clip, {e2e['moving_frames']} "
              f"with motion in the shutter), {e2e['samples'] / 1e6:.1f} M samples, {ref_spp}-spp references, {workers} "
              f"workers: {e2e['wall_s']:.0f} s ({e2e['cpu_s']:.0f} CPU-s) vs plain mi.render of the same frames "
              f"and samples {e2e['plain_wall_s']:.0f} s ({e2e['plain_cpu_s']:.0f} CPU-s): ratio {e2e['ratio']:.2f}, "
              f"per CPU-second {e2e['ratio_per_cpu_s']:.2f}, cores idle {100 * e2e['idle_core_share']:.0f}% "
              "(the throughput measure)", flush=True)
    first = runs[sizes[0]]
    cb_rate, cb_cpu_rate = _cornell_rates(mi, dr, res=sizes[0], max_depth=max_depth, workers=workers,
                                          threads=threads)
    out.update({"dataset_e2e": runs, "dataset_msamples_per_s": first["msamples_per_s"],
                "dataset_vs_mi_render": first["ratio"], "dataset_vs_mi_render_per_cpu_s": first["ratio_per_cpu_s"],
                "dataset_cornell_msamples_per_s": cb_rate, "dataset_vs_cornell": first["msamples_per_s"] / cb_rate,
                "dataset_vs_cornell_per_cpu_s": first["msamples_per_cpu_s"] / cb_cpu_rate})
    print(f"  dataset {sizes[0]}x{sizes[0]} vs the Cornell box at its size {cb_rate:.2f} Msamples/s: "
          f"{out['dataset_vs_cornell']:.2f} (content, not the pipeline)", flush=True)
    return out


def _frames_per_hour_section(*, res: int, workers: int, scene_gen: dict) -> dict:
    """:func:`frames_per_hour` at ``res``: figures, printed."""
    fph = frames_per_hour(res=res, workers=workers, scene_gen=scene_gen)
    out = {"frames_per_hour": fph["frames_per_hour"], "frames_per_hour_per_worker": fph["frames_per_hour_per_worker"],
           "frame_s_by_kind": fph["frame_s"]}
    print(f"  {res}x{res} frames/hour (default scene mix, 4096-spp references): "
          f"{fph['frames_per_hour']:.1f} on {workers} workers ({fph['frames_per_hour_per_worker']:.1f} a worker; "
          + ", ".join(f"{k} {v:.0f} s a frame" for k, v in fph["frame_s"].items()) + ")", flush=True)
    return out


def _memory_section(*, seed: int, kind: str, res: int) -> dict:
    """Seconds and peak resident memory of a child process that renders one whole ``res``x``res``x8
    frame (``_CHILD``): figures, printed."""
    r = subprocess.run([sys.executable, "-c", _CHILD, str(seed), kind, str(res), "8"],
                       capture_output=True, text=True, env=_env(), cwd=ROOT)
    tag = f"frame_{res}x{res}x8"
    if r.returncode != 0:
        raise RuntimeError(f"the {res}x{res} memory child failed: "
                           + "\n".join((r.stderr or "").strip().splitlines()[-5:]))
    child = json.loads(r.stdout.strip().splitlines()[-1])
    out = {f"{tag}_seconds": child["seconds"], f"{tag}_peak_gib": child["peak_rss_gib"]}
    print(f"  {res}x{res}x8 frame: peak memory {out[tag + '_peak_gib']:.2f} GiB "
          f"(target < {TARGET_PEAK_GIB} at 256x256), {out[tag + '_seconds']:.1f} s")
    return out


def run(*, seed: int = 0, kind: str = "indoor", res: int = 128, spp: int = 8, ref_passes: int = 4,
        ref_pass_spp: int = 128, repeats: int = 3, memory: bool = True, memory_res: int = 256,
        e2e_res=E2E_SIZES, e2e_ref_spp: int = 1024, e2e_warm: bool = True, e2e_workers: int | None = None, fph_res: int = 256,
        counts_res: int = 64, scene_gen: dict | None = None) -> dict:
    """Print and return the renderer's figures (dict of floats). ``memory_res``: the edge of the frame
    whose peak memory is measured in a child process (256 for the target; the tests use a tiny one);
    ``e2e_*``: the end-to-end dataset runs (``e2e_res``: their sizes; empty: skip); ``fph_res``: the frames-per-hour resolution (0: skip);
    ``counts_res``: the frame of :func:`kernel_counts` (8 spp; 0: skip);
    ``scene_gen``: overrides of the default config's scene generator (the tiny run's few objects)."""
    from pipeline.config import load_config

    workers = e2e_workers or max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 2)
    overrides = dict(scene_gen or {})
    scene_gen = {**load_config(DEFAULT_CONFIG).scene_gen, **overrides}
    ref_spp = ref_passes * ref_pass_spp
    spec, cfg, before_spec = _bench_scenes(seed=seed, kind=kind, res=res, spp=spp, ref_passes=ref_passes,
                                           ref_spp=ref_spp, scene_gen=scene_gen)
    cb_spp = 4 * spp
    # One scene alive at a time: drjit traces a virtual call for every instance alive in the process,
    # so a scene beside another renders slower (the Cornell box beside one generated scene: 2.4 against
    # 3.6 Msamples/s alone). Each comparison below loads its scenes in turn, frees them, and alternates.
    mi, dr, t = _loop_times(spec, cfg, spp=spp, ref_spp=ref_spp, ref_pass_spp=ref_pass_spp, repeats=repeats)
    t.update(_scene_times(mi, spec, cfg, before_spec, res=res, spp=cb_spp, repeats=repeats))
    scene = (f"{kind} seed {seed}, {len(spec.objects)} objects, {t['shapes']} shapes "
             f"({t['before_shapes']} before merging), {res}x{res}")
    out = _loop_figures(t, scene=scene, n_in=res * res * spp, n_ref=res * res * ref_spp, n_cb=res * res * cb_spp)
    if counts_res:
        out["launches"] = _launches_section(seed=seed, kind=kind, res=counts_res, scene_gen=scene_gen)
    if e2e_res:
        sizes = (e2e_res,) if isinstance(e2e_res, int) else tuple(e2e_res)
        out.update(_dataset_section(mi, dr, sizes=sizes, ref_spp=e2e_ref_spp, workers=workers,
                                    threads=t["threads"], scene_gen=scene_gen, max_depth=spec.max_depth,
                                    warm=e2e_warm))
    if fph_res:
        out.update(_frames_per_hour_section(res=fph_res, workers=workers, scene_gen=overrides))
    if memory:
        out.update(_memory_section(seed=seed, kind=kind, res=memory_res))
    return out


if __name__ == "__main__":
    run()
