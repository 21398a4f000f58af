"""``python -m pipeline estimate --config FILE [--workers N]``: what a dataset will cost, before it runs.

    python -m pipeline estimate --config configs/layer-paper.yaml --workers 64 [--scenes-per-group 1]
                                [--threads T] [--json FILE]

A short calibration renders a few of the config's own frames on this machine, with the config's
renderer settings and one drjit thread per worker thread (``cluster.threads_per_worker``, as a
dataset worker runs): frame 0 of the first ``--scenes-per-group`` scenes of every scene group, each
timed as the dataset's tasks spend it (scene load with mesh building and kernel compilation, the
full per-sample inputs, the full sample layers) and the reference from ``--ref-passes`` passes of
its production size (the rest of its passes are extrapolated: passes cost alike). Times are the CPU
seconds of the calibrating process, so other work on the machine does not inflate them. The calibration
frames are written to a temporary store with the config's layout to measure stored bytes.

It prints, for the whole dataset:

- samples: frames x pixels x (spp + layer samples + reference spp), the reference at its cap
  (``ref_spp``; with ``ref_target_rel_stderr`` frames may stop earlier, so the figure is a ceiling);
- core-hours at this machine's speed (the group's mean calibrated CPU seconds a frame x its frames);
- store bytes (calibrated bytes per frame x frames) and their share of raw float32;
- wall time on ``--workers`` N workers of this speed: core time / (N x threads), and never less than
  the slowest frame; scheduling, write and cluster start-up overheads are not included.

Error: the figures scale with the calibration frames, which are a handful of random scenes; half
of the scenes move (time slices cost more), so the mix of a few frames can differ from the whole
set. ``--scenes-per-group`` trades calibration time for a better mean.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path

from pipeline.errors import ConfigError



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
    p.add_argument("--ref-passes", type=int, default=2,
                   help="reference passes rendered per calibration frame (default 2; the rest are extrapolated)")
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


def calibrate(cfg, *, per_group: int = 1, ref_passes: int = 2, threads: int | None = None,
              log=print) -> dict:
    """Render the calibration frames of ``cfg`` (a :class:`pipeline.config.DatasetConfig`); returns
    per-frame timings (seconds) and stored bytes, and per-group means."""
    from pipeline import render as R
    from pipeline import tasks
    from scene_gen.spec import SceneSpec
    from stores.schema import create_store
    from stores.writer import StoreWriter

    if per_group < 1:
        raise ConfigError(f"--scenes-per-group must be >= 1, got {per_group}")
    rc = cfg.render_config()
    if ref_passes < 1 or (rc.ref_spp and ref_passes > rc.ref_passes):
        raise ConfigError(f"--ref-passes must be in [1, {rc.ref_passes}] (the config's ref_passes), got {ref_passes}")
    threads = threads or cfg.cluster.threads_per_worker
    rc = dataclasses.replace(rc, threads=int(threads))
    pass_spp = rc.ref_spp // rc.ref_passes if rc.ref_spp else 0
    cal_rc = (dataclasses.replace(rc, ref_passes=max(2, ref_passes), ref_min_passes=2, ref_target_rel_stderr=None,
                                  ref_spp=max(2, ref_passes) * pass_spp) if rc.ref_spp else rc)
    picks = _calibration_frames(cfg, per_group)
    frames, arrays = [], []
    render = {**cfg.render, "res": list(cfg.resolution)}
    for gi, ref in picks:
        # CPU seconds of this process (all its threads): the work a worker of this speed does,
        # whatever else runs on the machine; wall seconds are kept beside them
        w0, c0 = time.perf_counter(), time.process_time()
        spec_json = tasks.make_spec(ref.seed, ref.kind, ref.num_frames, tuple(cfg.resolution), dict(cfg.scene_gen))
        spec = SceneSpec.from_json(spec_json)
        fs = R.FrameScene(spec, ref.frame, rc)
        cpu = {"load_s": time.process_time() - c0}
        c = time.process_time()
        inputs = R.inputs_part(fs)
        cpu["inputs_s"], c = time.process_time() - c, time.process_time()
        layers = R.layers_part(fs)
        cpu["layers_s"], c = time.process_time() - c, time.process_time()
        if rc.ref_spp:
            fs.cfg = cal_rc
            ref_part = R.reference_part(fs)
            fs.cfg = rc
            cpu["reference_s"] = (time.process_time() - c) / cal_rc.ref_passes * rc.ref_passes
        else:
            ref_part = R.reference_part(fs)
            cpu["reference_s"] = time.process_time() - c
        wall = time.perf_counter() - w0
        ref_part = {**ref_part, "reference_spp": rc.ref_spp}
        frame = {"group": gi, "kind": ref.kind, "scene_seed": ref.seed, "objects": len(spec.objects),
                 "has_motion": spec.has_motion, **cpu, "calibration_wall_s": wall}
        frame["frame_s"] = sum(cpu.values())
        frames.append(frame)
        arrays.append(R.assemble(spec_json, ref.frame, inputs, layers, ref_part))
        log(f"  calibrated {ref.kind} scene {ref.scene} (seed {ref.seed}, {len(spec.objects)} objects"
            f"{', motion' if spec.has_motion else ''}): {frame['frame_s']:.1f} CPU-s a frame "
            f"(load {cpu['load_s']:.1f}, inputs {cpu['inputs_s']:.1f}, layers {cpu['layers_s']:.1f}, "
            f"reference {cpu['reference_s']:.1f} from {cal_rc.ref_passes if rc.ref_spp else 0} of "
            f"{rc.ref_passes} passes; calibrating it took {wall:.1f} s)")
    with tempfile.TemporaryDirectory(prefix="estimate-", dir=scratch_dir()) as tmp:
        path = Path(tmp) / "calibration.zarr"
        layout = cfg.store_layout().with_frames(len(arrays))
        create_store(str(path), layout, {})
        empty = _du(path)
        w = StoreWriter(str(path))
        for i, a in enumerate(arrays):
            w.write_frame(i, a)
        per_frame_bytes = (_du(path) - empty) / len(arrays)
        fixed_bytes = empty
    raw = sum(int(a[k].nbytes) for a in arrays for k in a if k != "meta") / len(arrays)
    groups = {}
    for f in frames:
        groups.setdefault(f["group"], []).append(f["frame_s"])
    return {"frames": frames, "threads": int(threads), "group_frame_s": {g: sum(v) / len(v) for g, v in groups.items()},
            "bytes_per_frame": per_frame_bytes, "store_fixed_bytes": fixed_bytes, "raw_bytes_per_frame": raw}


def predict(cfg, cal: dict, workers: int) -> dict:
    """Dataset figures from a calibration (:func:`calibrate`) for ``workers`` workers."""
    rc = cfg.render_config()
    W, H = cfg.resolution
    layer_samples = 2 ** rc.layer_levels - 1
    per_frame_samples = W * H * (rc.spp + layer_samples + rc.ref_spp)
    frames = cfg.num_frames
    threads = cal["threads"]
    core_s = sum(g.count * g.frames * cal["group_frame_s"][gi] for gi, g in enumerate(cfg.scenes))
    worker_s = core_s / threads                       # a worker's threads share a frame's work
    longest = max(f["frame_s"] for f in cal["frames"]) / threads
    wall = max(worker_s / max(1, workers), longest)
    store_bytes = cal["store_fixed_bytes"] + cal["bytes_per_frame"] * frames
    return {
        "frames": frames, "samples": per_frame_samples * frames,
        "samples_per_frame": {"inputs": W * H * rc.spp, "layers": W * H * layer_samples,
                              "reference_max": W * H * rc.ref_spp},
        "reference_early_stop": rc.ref_target_rel_stderr is not None,
        "core_hours": core_s / 3600.0, "worker_hours": worker_s / 3600.0,
        "store_bytes": int(store_bytes), "store_share_of_float32": cal["bytes_per_frame"] / cal["raw_bytes_per_frame"],
        "workers": int(workers), "threads_per_worker": threads, "wall_s": wall,
        "calibrated_samples_per_core_s": per_frame_samples * len(cal["frames"]) / sum(f["frame_s"] for f in cal["frames"]),
    }


def _default_workers(cfg) -> int:
    if cfg.cluster.workers:
        return int(cfg.cluster.workers)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // cfg.cluster.threads_per_worker)


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
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    W, H = cfg.resolution
    print(f"estimate for {args.config}: {cfg.num_scenes} scenes, {cfg.num_frames} frames at {W}x{H}", flush=True)
    t0 = time.perf_counter()
    cal = calibrate(cfg, per_group=args.scenes_per_group, ref_passes=args.ref_passes, threads=args.threads)
    p = predict(cfg, cal, workers)
    p["calibration_s"] = time.perf_counter() - t0
    rc = cfg.render_config()
    spf = p["samples_per_frame"]
    cap = "at most " if p["reference_early_stop"] else ""
    print(f"calibration: {len(cal['frames'])} frame(s) in {p['calibration_s']:.0f} s, {cal['threads']} drjit "
          f"thread(s) ({p['calibrated_samples_per_core_s'] / 1e6:.3f} M samples per core-second, everything included)")
    print(f"samples:     {cap}{p['samples']:.3g} ({spf['inputs']:.3g} inputs + {spf['layers']:.3g} layers + "
          f"{cap}{spf['reference_max']:.3g} reference a frame; {rc.spp}, {2 ** rc.layer_levels - 1} and "
          f"{rc.ref_spp} spp)")
    print(f"core-hours:  {cap}{p['core_hours']:.3g} at this machine's speed")
    print(f"store:       {_bytes(p['store_bytes'])} ({_bytes(cal['bytes_per_frame'])} a frame, "
          f"{p['store_share_of_float32']:.2f} of float32)")
    print(f"wall time:   {cap}{_hms(p['wall_s'])} on {workers} worker(s) x {cal['threads']} thread(s) of this "
          f"speed (scheduling and writes not included)")
    if p["reference_early_stop"]:
        print(f"             references stop early once their relative stderr is <= {rc.ref_target_rel_stderr}: "
              "frames that converge cost less")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"prediction": p, "calibration": cal}, f, indent=2, default=str)
    return 0
