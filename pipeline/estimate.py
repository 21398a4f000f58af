"""``python -m pipeline estimate --config FILE [--workers N]``: what a dataset will cost, before it runs.

    python -m pipeline estimate --config configs/layer-paper.yaml --workers 64 [--scenes-per-group 1]
                                [--threads T] [--concurrent C] [--ref-passes P] [--json FILE]

A short calibration renders a few of the config's own frames on this machine, with the config's
renderer settings and one drjit thread per worker thread (``cluster.threads_per_worker``, as a
dataset worker runs): frame 0 of the first ``--scenes-per-group`` scenes of every scene group, each
timed as the dataset's tasks spend it (scene load with mesh building and kernel compilation, the
full per-sample inputs, the full sample layers) and the reference from ``--ref-passes`` passes of
its production size (the rest is extrapolated: with ``reference: moments`` a launch's host cost and a
sample's cost are fitted to the calibration's reference and layers, which share the kernel, and the
frame's own shutter times and predicted rounds give the launches; with ``batch_means`` passes cost
alike). Times are the CPU
seconds of the calibrating process. The frames render ``--concurrent`` at a time in separate
processes (default: as many as the workers that share one machine, i.e. this machine's cores /
threads per worker, at most ``--workers``), as a machine's workers do, so that whatever they cost
each other (memory bandwidth, shared caches, a CPU's power budget) is in the figures. With an early-stopping
reference (``ref_target_rel_stderr``) each frame's stop is predicted from its first passes
(:func:`predicted_passes`). The calibration frames are written to a temporary store with the
config's layout to measure stored bytes.

It prints, for the whole dataset:

- samples: frames x pixels x (spp + layer samples + reference spp): expected (the predicted reference
  stops) and at most (every reference at ``ref_spp``);
- core-hours at this machine's speed (the group's mean calibrated CPU seconds a frame x its frames);
- store bytes (calibrated bytes per frame x frames) and their share of raw float32;
- wall time on ``--workers`` N workers of this speed: core time / (N x threads), and never less than
  the slowest frame; plus the measured start-up of the calibration's worker processes. Scheduling,
  cluster start and validation are not included.

Error: the figures scale with the calibration frames, which are a handful of random scenes; half
of the scenes move (time slices cost more), so the mix of a few frames can differ from the whole
set. ``--scenes-per-group`` trades calibration time for a better mean. Against a real run of
``configs/train-cpu.yaml`` on this 2-core machine (issue 13): samples -10.6%, store bytes +2.7%,
core-hours 0% (per kind -15% and +34%) and wall -2% (docs/throughput.md).
"""
from __future__ import annotations

import importlib
import argparse
import dataclasses
import json
import math
import os
import tempfile
import time
from pathlib import Path

from pipeline.errors import ConfigError
from core.checks import need


def scratch_dir() -> str | None:
    """``$DENOISE_DATA`` (the Makefile's data folder; created if missing, as on a fresh clone), else the
    system's temporary folder."""
    d = os.environ.get("DENOISE_DATA")
    if d:
        os.makedirs(d, exist_ok=True)
    return d or None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, help="dataset YAML")
    p.add_argument("--workers", type=int, default=None,
                   help="workers to predict the wall time for (default: the config's, else one per core here)")
    p.add_argument("--scenes-per-group", type=int, default=1,
                   help="calibration scenes from each scene group of the config (default 1)")
    p.add_argument("--ref-passes", type=int, default=None,
                   help="reference passes rendered per calibration frame (default 2, or 4 when references stop "
                        "early: the stop is predicted from them; the rest are extrapolated)")
    p.add_argument("--concurrent", type=int, default=None,
                   help="calibration renders side by side, as a machine's workers run (default: as many as the "
                        "predicted workers, at most this machine's cores / threads per worker)")
    p.add_argument("--threads", type=int, default=None,
                   help="drjit threads while calibrating (default: the config's cluster.threads_per_worker)")
    p.add_argument("--json", help="also write the figures to this JSON file")


def _calibration_frames(cfg, per_group: int) -> list:
    """Frame 0 of the first ``per_group`` scenes of every group (``pipeline.config.FrameRef``), with
    the group's index."""
    out, by_scene = [], {}
    for ref in cfg.frames():
        by_scene.setdefault(ref.scene, ref) if ref.frame == 0 else None
    s = 0
    for gi, g in enumerate(cfg.scenes):
        for j in range(g.count):
            if j < per_group:
                out.append((gi, by_scene[s]))
            s += 1
    return out


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def c4(n: int) -> float:
    """E[s] / sigma for the sample standard deviation ``s`` of ``n`` normal values (ddof 1)."""
    return math.sqrt(2.0 / (n - 1)) * math.exp(math.lgamma(n / 2.0) - math.lgamma((n - 1) / 2.0))


def predicted_passes(rel: float, done: int, rc) -> int:
    """Reference passes until the early stop of ``rc`` (``pipeline.render.render_reference``), from the
    relative standard error ``rel`` measured after ``done`` passes.

    The batch-means error falls as 1/sqrt(passes); the stop compares the *estimated* error, whose
    mean is ``c4(p)`` times the true one, so ``rel(p) = rel / c4(done) * c4(p) * sqrt(done / p)``.
    Without a target (or a reference) every pass runs."""
    if rc.ref_target_rel_stderr is None or rc.ref_spp == 0:
        return rc.ref_passes
    if rc.reference == "moments":
        return predicted_rounds(rel, done, rc)[-1]
    sigma = rel / c4(done) * math.sqrt(done)
    for p in range(rc.ref_min_passes, rc.ref_passes):
        if sigma * c4(p) / math.sqrt(p) <= rc.ref_target_rel_stderr:
            return p
    return rc.ref_passes


def predicted_rounds(rel: float, done: int, rc) -> list[int]:
    """The passes after each round of a ``moments`` reference (``pipeline.render.reference._reference_moments``)
    whose relative standard error is ``rel`` after ``done`` passes: its error has thousands of degrees
    of freedom, so it is taken as exact and falls as 1/sqrt(passes). Without a target: one round."""
    if rc.ref_target_rel_stderr is None or rc.ref_spp == 0:
        return [rc.ref_passes]
    sigma, target = rel * math.sqrt(done), rc.ref_target_rel_stderr
    out = [rc.ref_min_passes]
    while out[-1] < rc.ref_passes:
        r = sigma / math.sqrt(out[-1])
        if r <= target:
            break
        out.append(min(rc.ref_passes, max(out[-1] + 1, math.ceil(out[-1] * (r / target) ** 2 * 1.05))))
    return out


def reference_seconds(t_cal: float, cal_spp: int, cal_launches: int, t_layers: float, layer_spp: int,
                      layer_launches: int, spp: int, launches: int) -> float:
    """Seconds of a ``moments`` reference of ``spp`` samples a pixel in ``launches`` launches, from the
    calibration's reference (``cal_spp`` in ``cal_launches``) and layers (the same kernel: ``layer_spp``
    in ``layer_launches``): ``t = launches * a + spp * b`` fitted to both. A launch costs the same
    host work whatever its samples (``set_time``, tracing, the launch), so scaling the calibration by
    samples alone would count its launches as often as its samples. Where the two points do not give
    positive costs (noise), by samples alone."""
    det = layer_launches * cal_spp - cal_launches * layer_spp
    if det:
        a = (t_layers * cal_spp - t_cal * layer_spp) / det
        b = (layer_launches * t_cal - cal_launches * t_layers) / det
        if a >= 0 and b > 0:
            return launches * a + spp * b
    return t_cal * spp / max(cal_spp, 1)


def _warm_worker(threads: int, cache_dir: str | None = None) -> None:
    """Process-pool initializer: imports, drjit's thread pool and LLVM's start (a tiny Cornell box
    render) before any task is timed (they count in the printed start-up). ``cache_dir``: drjit's
    kernel cache for this process (``DRJIT_CACHE_DIR``, read when drjit starts), an empty folder so
    that every calibration frame compiles its kernels as a new scene in a dataset run does, not load
    them from an earlier run."""
    if cache_dir:
        os.environ["DRJIT_CACHE_DIR"] = cache_dir
    from core.variant import mitsuba
    mi = mitsuba(threads=threads)
    importlib.import_module("pipeline.render")     # its import cost is the calibration's, not a frame's
    d = mi.cornell_box()
    d["sensor"]["film"].update(width=4, height=4)
    scene = mi.load_dict(d)
    mi.render(scene, spp=1)
    del scene, d                    # no instance left to grow the calibration frames' kernels
    import gc
    gc.collect()


def _calibrate_frame(cfg, gi: int, ref, rc, cal_rc) -> tuple[dict, dict]:
    """Render one calibration frame as the dataset's tasks do; (its timings, its frame dict)."""
    from pipeline import render as R
    from pipeline import tasks
    from scene_gen.spec import SceneSpec

    # CPU seconds of this process (all its threads): the work a worker of this speed does; wall seconds
    # are kept beside them
    w0, c0 = time.perf_counter(), time.process_time()
    made_of = ref.source if ref.source is not None else dict(cfg.scene_gen)      # a scene file's, or the generator's
    spec_json = tasks.make_spec(ref.seed, ref.kind, ref.num_frames, tuple(cfg.resolution), made_of, ref.case)
    spec = SceneSpec.from_json(spec_json)
    fs = R.FrameScene(spec, ref.frame, rc)
    cpu = {"load_s": time.process_time() - c0}
    c = time.process_time()
    inputs = R.inputs_part(fs)
    cpu["inputs_s"], c = time.process_time() - c, time.process_time()
    layers = R.layers_part(fs)
    cpu["layers_s"], c = time.process_time() - c, time.process_time()
    passes = rc.ref_passes
    if rc.ref_spp:
        fs.cfg = cal_rc
        ref_part = R.reference_part(fs)
        fs.cfg = rc
        t_cal = time.process_time() - c
        passes = predicted_passes(ref_part["reference_rel_stderr"], cal_rc.ref_passes, rc)
        if rc.reference == "moments":
            pass_spp, T = rc.ref_spp // rc.ref_passes, ref_part["ref_time_slices"]
            rounds = len(predicted_rounds(ref_part["reference_rel_stderr"], cal_rc.ref_passes, rc))
            lay = [fs.slices_for(2 ** n) for n in range(rc.layer_levels)]
            cpu["reference_s"] = reference_seconds(t_cal, cal_rc.ref_spp, T, cpu["layers_s"], 2 ** rc.layer_levels - 1,
                                                   sum(lay), passes * pass_spp, rounds * T)
        else:
            cpu["reference_s"] = t_cal / cal_rc.ref_passes * passes
    else:
        ref_part = R.reference_part(fs)
        cpu["reference_s"] = time.process_time() - c
    wall = time.perf_counter() - w0
    ref_part = {**ref_part, "reference_spp": rc.ref_spp}
    frame = {"group": gi, "kind": ref.kind, "scene": ref.scene, "scene_seed": ref.seed, "objects": len(spec.objects),
             "has_motion": spec.has_motion, **cpu, "calibration_wall_s": wall,
             "reference_passes": passes, "reference_spp": passes * (rc.ref_spp // rc.ref_passes) if rc.ref_spp else 0}
    frame["frame_s"] = sum(cpu.values())
    del fs                              # free the scene before this process calibrates another
    import gc
    gc.collect()
    return frame, R.assemble(spec_json, ref.frame, inputs, layers, ref_part)


def local_slots(threads: int) -> int:
    """Workers of ``threads`` threads that fill this machine's cores."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // max(1, threads))


def calibrate(cfg, *, per_group: int = 1, ref_passes: int | None = None, threads: int | None = None,
              concurrent: int = 1, log=print) -> dict:
    """Render the calibration frames of ``cfg`` (a :class:`pipeline.config.DatasetConfig`); returns
    per-frame timings (seconds) and stored bytes, and per-group means.

    The frames render in ``concurrent`` fresh processes side by side, as a machine's workers do in a
    real run, so the figures include what they cost each other; each process starts with an empty
    drjit kernel cache, so a frame's time includes compiling its scene's kernels, as every new scene of
    a run does. The frame list is padded with repeats to a multiple of ``concurrent`` so that every
    frame is timed under the same load; a frame's figures are its first run's. ``ref_passes``:
    reference passes rendered per frame (default 2; 4 with an early stop, whose pass count is
    predicted from them, :func:`predicted_passes`).
    """
    need(per_group >= 1, "--scenes-per-group", ">= 1", per_group, ConfigError)
    need(concurrent >= 1, "--concurrent", ">= 1", concurrent, ConfigError)
    threads = int(threads or cfg.cluster.threads_per_worker)
    rc, cal_rc = _calibration_configs(cfg, ref_passes, threads)
    picks = _calibration_frames(cfg, per_group)
    runs, arrays, start_s = _render_calibration(cfg, picks, rc, cal_rc, threads, concurrent, log)
    # a frame's first run is its figure: a repeat (it keeps the last frames under load) finds the kernels
    # compiled by then
    frames = [{**runs[i][0], "runs": len(runs[i])} for i in range(len(picks))]
    per_frame_bytes, fixed_bytes = _stored_bytes(cfg, [arrays[i] for i in range(len(picks))])
    raw = sum(int(a[k].nbytes) for a in arrays.values() for k in a if k != "meta") / len(picks)
    groups: dict[int, list] = {}
    for f in frames:
        groups.setdefault(f["group"], []).append(f)
    mean = lambda fs, k: sum(f[k] for f in fs) / len(fs)      # noqa: E731
    return {"frames": frames, "threads": threads, "concurrent": int(concurrent), "start_s": start_s,
            "group_frame_s": {g: mean(v, "frame_s") for g, v in groups.items()},
            "group_reference_spp": {g: mean(v, "reference_spp") for g, v in groups.items()},
            "bytes_per_frame": per_frame_bytes, "store_fixed_bytes": fixed_bytes, "raw_bytes_per_frame": raw}


def _calibration_configs(cfg, ref_passes: int | None, threads: int) -> tuple:
    """``(rc, cal_rc)``: the config's render settings on ``threads`` drjit threads, and the same with a
    reference of ``ref_passes`` passes of its production size, without an early stop (the default:
    2 passes, 4 when the reference stops early, so its stop can be predicted)."""
    rc = cfg.render_config()
    if ref_passes is None:
        ref_passes = min(4 if rc.ref_target_rel_stderr is not None else 2, max(2, rc.ref_passes))
    need(ref_passes >= 1 and not (rc.ref_spp and ref_passes > rc.ref_passes), "--ref-passes",
         f"in [1, {rc.ref_passes}] (the config's ref_passes)", ref_passes, ConfigError)
    rc = dataclasses.replace(rc, threads=threads)
    if not rc.ref_spp:
        return rc, rc
    passes = max(2, ref_passes)
    return rc, dataclasses.replace(rc, ref_passes=passes, ref_min_passes=2, ref_target_rel_stderr=None,
                                   ref_spp=passes * (rc.ref_spp // rc.ref_passes))


def _log_frame(frame: dict, rc, cal_rc, log) -> None:
    log(f"  calibrated {frame['kind']} scene {frame['scene']} (seed {frame['scene_seed']}, {frame['objects']} "
        f"objects{', motion' if frame['has_motion'] else ''}): {frame['frame_s']:.1f} CPU-s a frame "
        f"(load {frame['load_s']:.1f}, inputs {frame['inputs_s']:.1f}, layers {frame['layers_s']:.1f}, "
        f"reference {frame['reference_s']:.1f} for {frame['reference_passes']} of {rc.ref_passes} passes, "
        f"timed on {cal_rc.ref_passes if rc.ref_spp else 0}; took {frame['calibration_wall_s']:.1f} s)")


def _render_calibration(cfg, picks: list, rc, cal_rc, threads: int, concurrent: int, log) -> tuple:
    """Render every pick in ``concurrent`` fresh processes, the list padded with repeats to a multiple
    of ``concurrent``; ``(runs, arrays, start_s)``: each pick's timings of every run, its first run's
    frame dict, and the seconds the processes took to start."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    jobs = list(range(len(picks)))
    if concurrent > 1:
        jobs += [i % len(picks) for i in range(-len(jobs) % concurrent)]
        log(f"  {len(jobs)} calibration render(s) in {concurrent} processes side by side "
            f"({len(jobs) - len(picks)} repeat(s) keep every frame under the same load)")
    runs: dict[int, list] = {}
    arrays: dict[int, dict] = {}
    w0 = time.perf_counter()
    # fresh processes with an empty kernel cache: a frame pays its scene's kernel compilation, as every
    # new scene of a run does (drjit would otherwise load kernels compiled by an earlier calibration)
    with tempfile.TemporaryDirectory(prefix="estimate-kernels-", dir=scratch_dir()) as kernels, \
            ProcessPoolExecutor(concurrent, multiprocessing.get_context("spawn"), initializer=_warm_worker,
                                initargs=(threads, kernels)) as pool:
        list(pool.map(time.sleep, [0.0] * concurrent))        # start-up: the processes, imports, drjit
        start_s = time.perf_counter() - w0
        futs = [(i, pool.submit(_calibrate_frame, cfg, *picks[i], rc, cal_rc)) for i in jobs]
        for i, f in futs:
            frame, arr = f.result()
            if i not in runs:
                _log_frame(frame, rc, cal_rc, log)
            runs.setdefault(i, []).append(frame)
            arrays.setdefault(i, arr)
    return runs, arrays, start_s


def _stored_bytes(cfg, frames: list[dict]) -> tuple[float, int]:
    """``(bytes a frame, bytes of the empty store)``: ``frames`` written to a temporary store of the
    config's layout."""
    from stores.create import create_store
    from stores.writer import StoreWriter

    with tempfile.TemporaryDirectory(prefix="estimate-", dir=scratch_dir()) as tmp:
        path = Path(tmp) / "calibration.zarr"
        create_store(str(path), cfg.store_layout().with_frames(len(frames)), {})
        empty = _du(path)
        w = StoreWriter(str(path))
        for i, arrays in enumerate(frames):
            w.write_frame(i, arrays)
        return (_du(path) - empty) / len(frames), empty


def predict(cfg, cal: dict, workers: int) -> dict:
    """Dataset figures from a calibration (:func:`calibrate`) for ``workers`` workers."""
    rc = cfg.render_config()
    W, H = cfg.resolution
    layer_samples = 2 ** rc.layer_levels - 1
    per_frame_samples = W * H * (rc.spp + layer_samples + rc.ref_spp)
    frames = cfg.num_frames
    threads = cal["threads"]
    groups = list(enumerate(cfg.scenes))
    frame_s = {int(k): v for k, v in cal["group_frame_s"].items()}       # int keys, also after a JSON round trip
    ref_spp = {int(k): v for k, v in (cal.get("group_reference_spp") or {gi: rc.ref_spp for gi, _ in groups}).items()}
    core_s = sum(g.count * g.frames * frame_s[gi] for gi, g in groups)
    expected = sum(g.count * g.frames * W * H * (rc.spp + layer_samples + ref_spp[gi]) for gi, g in groups)
    worker_s = core_s / threads                       # a worker's threads share a frame's work
    longest = max(f["frame_s"] for f in cal["frames"]) / threads
    wall = max(worker_s / max(1, workers), longest)
    store_bytes = cal["store_fixed_bytes"] + cal["bytes_per_frame"] * frames
    return {
        "frames": frames, "samples": per_frame_samples * frames, "samples_expected": int(expected),
        "samples_per_frame": {"inputs": W * H * rc.spp, "layers": W * H * layer_samples,
                              "reference_max": W * H * rc.ref_spp},
        "reference_early_stop": rc.ref_target_rel_stderr is not None,
        "core_hours": core_s / 3600.0, "worker_hours": worker_s / 3600.0,
        "store_bytes": int(store_bytes), "store_share_of_float32": cal["bytes_per_frame"] / cal["raw_bytes_per_frame"],
        "workers": int(workers), "threads_per_worker": threads, "wall_s": wall,
        "start_s": float(cal.get("start_s", 0.0)),
        "calibrated_samples_per_core_s": sum(W * H * (rc.spp + layer_samples + f.get("reference_spp", rc.ref_spp))
                                             for f in cal["frames"]) / sum(f["frame_s"] for f in cal["frames"]),
    }


def _default_workers(cfg) -> int:
    if cfg.cluster.workers:
        return int(cfg.cluster.workers)
    return local_slots(cfg.cluster.threads_per_worker)


def _hms(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    if s < 3 * 86400:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} days"


def _bytes(n: float) -> str:
    for unit, k in (("TiB", 2 ** 40), ("GiB", 2 ** 30), ("MiB", 2 ** 20), ("KiB", 2 ** 10)):
        if n >= k:
            return f"{n / k:.1f} {unit}"
    return f"{n:.0f} B"


def run(args) -> int:
    from pipeline.config import load_config
    cfg = load_config(args.config)
    workers = args.workers if args.workers is not None else _default_workers(cfg)
    need(workers >= 1, "--workers", ">= 1", workers, ConfigError)
    threads = args.threads or cfg.cluster.threads_per_worker
    concurrent = args.concurrent if args.concurrent is not None else min(workers, local_slots(threads))
    cfg.check_memory(workers=concurrent)       # the calibration renders its frames in this machine's memory
    W, H = cfg.resolution
    print(f"estimate for {args.config}: {cfg.num_scenes} scenes, {cfg.num_frames} frames at {W}x{H}", flush=True)
    t0 = time.perf_counter()
    cal = calibrate(cfg, per_group=args.scenes_per_group, ref_passes=args.ref_passes, threads=threads,
                    concurrent=concurrent)
    p = predict(cfg, cal, workers)
    p["calibration_s"] = time.perf_counter() - t0
    rc = cfg.render_config()
    spf = p["samples_per_frame"]
    early = p["reference_early_stop"]
    print(f"calibration: {len(cal['frames'])} frame(s) in {p['calibration_s']:.0f} s, {cal['threads']} drjit "
          f"thread(s), {cal['concurrent']} side by side ({p['calibrated_samples_per_core_s'] / 1e6:.3f} M samples "
          "per core-second, everything included)")
    print(f"samples:     {p['samples_expected']:.3g}" + (f" expected, at most {p['samples']:.3g}" if early else "")
          + f" ({spf['inputs']:.3g} inputs + {spf['layers']:.3g} layers + at most {spf['reference_max']:.3g} "
          f"reference a frame; {rc.spp}, {2 ** rc.layer_levels - 1} and {rc.ref_spp} spp)")
    print(f"core-hours:  {p['core_hours']:.3g} at this machine's speed")
    print(f"store:       {_bytes(p['store_bytes'])} ({_bytes(cal['bytes_per_frame'])} a frame, "
          f"{p['store_share_of_float32']:.2f} of float32)")
    print(f"wall time:   {_hms(p['wall_s'])} on {workers} worker(s) x {cal['threads']} thread(s) of this "
          f"speed, plus start-up (here {p['start_s']:.0f} s for {cal['concurrent']} worker process(es)); scheduling "
          "and validation not included")
    if early:
        print(f"             references stop once their relative stderr is <= {rc.ref_target_rel_stderr} (at least "
              f"{rc.ref_min_passes} of {rc.ref_passes} passes): the stop is predicted from each calibration frame's "
              "first passes")
    if args.scenes_per_group == 1 and any(g.count > 1 for g in cfg.scenes):
        passes = f" --ref-passes {min(8, rc.ref_passes)}" if rc.ref_spp and rc.ref_passes > 4 else ""
        print("note:        one calibration scene a group; scenes of a kind differ up to 2x in frame time, and a "
              f"stop predicted from few passes runs short: --scenes-per-group 3{passes} gives a closer figure "
              "for a longer calibration (docs/cluster.md)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"prediction": p, "calibration": cal}, f, indent=2, default=str)
    return 0
