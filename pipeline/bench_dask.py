"""Benchmark of the Dask stage (``make bench`` → ``pipeline.bench`` → :func:`run`).

Figures printed:

- **frames/minute with 1 and 2 workers** (LocalCluster, one thread each, drjit sized to it): the same
  dataset graph (spec → render → write, into a temporary store; split tasks when the config splits)
  after every worker has rendered a warm-up frame (imports, mesh code, drjit kernels), so the figure is the
  steady state of a long run of new scenes: each run's workers start with an empty drjit kernel cache
  and compile their scenes' kernels, as a dataset's workers do. 12 frames (6 gave 1.6-1.8x from run to
  run). Tasks as the config default cuts them (whole frames). Target: 2 workers >= 1.7x one worker
  on 2 cores.
- **scheduler overhead per task**: the wall time per task of many no-op tasks on the 2-worker cluster
  (scheduling, messaging, bookkeeping) against the mean render task's duration from the task stream.
  Target: < 2 % of the render time.
- **efficiency**: summed task compute time / (wall time x workers) of the real graph.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path


def _noop(i):
    return i


def bench_config(frames: int, res: int, ref_spp: int, objects: int = 20):
    """``frames`` stills (half indoor) of ``res`` x ``res``; ``objects`` indoor meshes (1.5x outdoor)."""
    from pipeline.config import DatasetConfig
    half = max(1, frames // 2)
    scenes = [{"kind": "indoor", "count": half}] + ([{"kind": "outdoor", "count": frames - half}]
                                                     if frames > half else [])
    return DatasetConfig.from_dict({
        "name": "bench-dask", "seed": 99, "resolution": [res, res], "scenes": scenes,
        "render": {"spp": 8, "layer_levels": 6, "ref_spp": ref_spp, "ref_passes": 16, "ref_min_passes": 16},
        "scene_gen": {"indoor_objects": objects, "outdoor_objects": (3 * objects) // 2},
        "tasks": {"retries": 0}, "cluster": {"dashboard_address": None}})


def _warm_up(cfg) -> None:
    """Render one frame of each kind (other seeds than the benchmark's) in this worker."""
    from pipeline import tasks
    render = {**cfg.render, "res": list(cfg.resolution)}
    for seed, kind in ((10 ** 6, "indoor"), (10 ** 6 + 1, "outdoor")):
        spec = tasks.make_spec(seed, kind, 1, cfg.resolution, cfg.scene_gen)
        tasks.render_reference(spec, 0, render)
        tasks.render_layers(spec, 0, render)
        tasks.render_inputs(spec, 0, render)
    return None


def _run_once(cfg, workers: int, root: Path, noop_tasks: int = 400) -> dict:
    """One timed run on a LocalCluster made as ``python -m pipeline dataset`` makes it
    (``pipeline.cluster.connect``: worker environment, main-thread imports, one thread a worker)."""
    from distributed import get_task_stream

    from pipeline.cluster import connect
    from pipeline.graph import build_graph
    from stores.writer import open_or_create
    store = str(root / f"w{workers}.zarr")
    # each run's workers start with an empty drjit kernel cache: the run before would otherwise have
    # compiled the same scenes' kernels for this one (a run of new scenes compiles them; 1 worker
    # against 2 read 15 against 51 frames/min, 3.3x, with the first run paying for both)
    kernels = root / f"kernels-{workers}"
    kernels.mkdir()
    old_cache = os.environ.get("DRJIT_CACHE_DIR")
    os.environ["DRJIT_CACHE_DIR"] = str(kernels)      # LocalCluster worker processes inherit it
    try:
        conn = connect(cfg.cluster, workers=workers)
    finally:
        if old_cache is None:
            os.environ.pop("DRJIT_CACHE_DIR", None)
        else:
            os.environ["DRJIT_CACHE_DIR"] = old_cache
    try:
        c = conn.client
        c.run(_warm_up, cfg)
        open_or_create(store, cfg.store_layout(), cfg.content_dict())
        g = build_graph(cfg, store)
        with get_task_stream(client=c) as ts:
            t0 = time.perf_counter()
            futs = g.submit(c)
            writes = [futs[k] for k in g.writes.values()]
            del futs
            c.gather(writes)
            wall = time.perf_counter() - t0
        compute = {}
        for t in ts.data:
            for s in t.get("startstops", ()):
                if s["action"] == "compute":
                    stage = str(t["key"]).split("-scene")[0]
                    compute.setdefault(stage, []).append(s["stop"] - s["start"])
        out = {"workers": workers, "frames": cfg.num_frames, "wall_s": wall,
               "frames_per_min": 60.0 * cfg.num_frames / wall,
               "task_s": {k: sum(v) / len(v) for k, v in compute.items()},
               "efficiency": sum(map(sum, compute.values())) / (wall * workers)}
        if workers > 1:
            n = noop_tasks
            t0 = time.perf_counter()
            c.gather(c.map(_noop, range(n), pure=False))
            out["overhead_per_task_s"] = (time.perf_counter() - t0) * workers / n
    finally:
        conn.close()
    return out


def run(frames: int = 12, res: int = 32, ref_spp: int = 256, objects: int = 20, noop_tasks: int = 400) -> dict:
    """Frames/minute with 1 and 2 workers and the scheduler's overhead per task; prints and returns them.
    (``make bench`` runs the defaults; the tests run ``frames=2, res=8, ref_spp=16, objects=3``.)"""
    cfg = bench_config(frames, res, ref_spp, objects)
    root = Path(tempfile.mkdtemp(prefix="bench-dask-"))
    try:
        one = _run_once(cfg, 1, root, noop_tasks)
        two = _run_once(cfg, 2, root, noop_tasks)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    render_tasks = [v for k, v in two["task_s"].items() if k in ("inputs", "layers", "reference", "render")]
    mean_render = sum(render_tasks) / max(1, len(render_tasks))
    res_ = {
        "config": {"frames": frames, "res": res, "spp": 8, "layers": 6, "ref_spp": ref_spp},
        "frames_per_min_1_worker": round(one["frames_per_min"], 3),
        "frames_per_min_2_workers": round(two["frames_per_min"], 3),
        "speedup_2_vs_1": round(two["frames_per_min"] / one["frames_per_min"], 3),
        "speedup_target": 1.7,
        "mean_task_s": {k: round(v, 3) for k, v in two["task_s"].items()},
        "scheduler_overhead_per_task_ms": round(1e3 * two["overhead_per_task_s"], 3),
        "overhead_vs_render_task": round(two["overhead_per_task_s"] / mean_render, 5) if mean_render else None,
        "overhead_target": 0.02,
        "efficiency_1_worker": round(one["efficiency"], 3),
        "efficiency_2_workers": round(two["efficiency"], 3),
    }
    print(f"dask: {frames} frames of {res}x{res} (8 spp, layers to 32 spp, {ref_spp}-spp reference), "
          f"{'split' if cfg.tasks.split else 'whole-frame'} tasks (the config default)")
    print(f"  1 worker : {res_['frames_per_min_1_worker']:.2f} frames/min (efficiency {one['efficiency']:.0%})")
    print(f"  2 workers: {res_['frames_per_min_2_workers']:.2f} frames/min (efficiency {two['efficiency']:.0%}) "
          f"-> {res_['speedup_2_vs_1']:.2f}x (target >= 1.7x)")
    print("  mean task seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in res_["mean_task_s"].items()))
    print(f"  scheduler overhead: {res_['scheduler_overhead_per_task_ms']:.2f} ms per task = "
          f"{100 * (res_['overhead_vs_render_task'] or 0):.3f} % of a mean render task (target < 2 %)")
    return res_


if __name__ == "__main__":
    run()
