"""Reference benchmark (``python -m pipeline bench --only reference``; part of ``make bench``): figures.

On the end-to-end bench's four frames (``pipeline.bench_render.end_to_end``: the same dataset seed,
scene generator and 64x64 1,024-spp references):

- **launches and seconds** of each frame's reference, ``moments`` (shutter times by the frame's motion)
  against ``batch_means`` (32 passes of 4 times: the method before), with the ``set_time`` calls and
  their milliseconds (moving the objects and rebuilding the acceleration structure);
- **host against kernel milliseconds** of the ``moments`` reference (drjit's kernel history:
  ``execution_time`` of every launch is kernel time, the rest of the wall time is host work: tracing,
  code generation, ``set_time``, the launches themselves), and that split projected for a GPU, whose
  kernels run at the CUDA rate measured in ../shared/NOTES.md (H200, ``mi.render`` at 512x512: 40.6
  Msamples/s at 8 spp, 101.3 at 256 spp) while the host work stays as measured here;
- **the z tests**: two references of one frame with independent render seeds,
  ``z = (a - b) / sqrt(se_a^2 + se_b^2)`` per pixel and channel (target: standard deviation within
  0.85 to 1.15, fewer than 1% of |z| > 3), on a static frame and a moving one, and the moving frame's
  reference against a dense-time one (256 shutter times).
"""
from __future__ import annotations

import contextlib
import dataclasses
import time

import numpy as np

from pipeline.bench_render import DEFAULT_CONFIG, _collect

GPU_MSAMPLES_PER_S = (40.6, 101.3)        # ../shared/NOTES.md: H200, mi.render at 512x512, 8 and 256 spp
Z_STD = (0.85, 1.15)
Z_TAIL = 0.01


def bench_frames(*, res: int, scene_gen: dict | None = None) -> list[tuple[str, object]]:
    """``(label, SceneSpec)`` of the end-to-end bench's four frames at ``res``."""
    from pipeline import tasks
    from pipeline.config import DatasetConfig, load_config
    from scene_gen.spec import SceneSpec
    gen = {**load_config(DEFAULT_CONFIG).scene_gen, **(scene_gen or {})}
    cfg = DatasetConfig.from_dict({"name": "bench-e2e", "seed": 4242, "resolution": [res, res],
                                   "scenes": [{"kind": "indoor", "count": 2}, {"kind": "outdoor", "count": 2}],
                                   "scene_gen": gen})
    out = []
    for f in cfg.frames():
        spec = SceneSpec.from_json(tasks.make_spec(f.seed, f.kind, f.num_frames, (res, res), gen, f.case))
        out.append((f"{f.kind} {f.seed}", spec))
    return out


@contextlib.contextmanager
def counted(fs):
    """Count ``fs``'s ``mi.render`` calls and its ``set_time`` moves (with their seconds) inside the block:
    yields ``{'launches', 'moves', 'move_s'}``."""
    c = {"launches": 0, "moves": 0, "move_s": 0.0}
    mi, loaded_set_time = fs.mi, fs.loaded.set_time

    class Module:
        def __getattr__(self, name):
            return getattr(mi, name)

        def render(self, *a, **k):
            c["launches"] += 1
            return mi.render(*a, **k)

    def set_time(t):
        moves = fs.loaded._time != t and fs.has_motion
        t0 = time.perf_counter()
        loaded_set_time(t)
        if moves:
            c["moves"] += 1
            c["move_s"] += time.perf_counter() - t0
    fs.mi, fs.loaded.set_time = Module(), set_time
    try:
        yield c
    finally:
        fs.mi = mi
        del fs.loaded.set_time


def z_scores(a: dict, b: dict) -> np.ndarray:
    """``(a - b) / sqrt(se_a^2 + se_b^2)`` of two references where either has an error."""
    se = np.sqrt(a["reference_stderr"].astype(np.float64) ** 2 + b["reference_stderr"].astype(np.float64) ** 2)
    ok = se > 0
    return (a["reference"].astype(np.float64) - b["reference"])[ok] / se[ok]


def z_figures(z: np.ndarray) -> dict:
    std, tail = float(z.std()), float(np.mean(np.abs(z) > 3))
    return {"std": std, "tail": tail, "values": int(z.size),
            "pass": bool(Z_STD[0] <= std <= Z_STD[1] and tail < Z_TAIL)}


def _host_and_kernel(fs) -> dict:
    """The ``moments`` reference of ``fs`` timed with drjit's kernel history: wall, kernel and host ms."""
    from pipeline import render as R
    dr = fs.dr
    R.render_reference(fs)                      # kernels compiled (or loaded) first
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        t0 = time.perf_counter()
        with counted(fs) as c:
            out = R.render_reference(fs)
        wall = time.perf_counter() - t0
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    kernel = sum(float(k.get("execution_time", 0.0)) for k in hist) / 1e3
    codegen = sum(float(k.get("codegen_time", 0.0)) + float(k.get("backend_time", 0.0)) for k in hist) / 1e3
    return {"wall_s": wall, "kernel_s": kernel, "host_s": max(wall - kernel, 0.0), "codegen_s": codegen,
            "set_time_s": c["move_s"], "launches": c["launches"], "times": out["ref_time_slices"]}


def frame_figures(spec, cfg) -> dict:
    """One frame's reference both ways: launches, moves, seconds; host and kernel time of ``moments``."""
    from pipeline import render as R
    fs = R.FrameScene(spec, 0, cfg)
    out = {"has_motion": bool(fs.has_motion), "displacement_px": float(fs.displacement)}
    for name, c in (("moments", cfg), ("batch_means", dataclasses.replace(cfg, reference="batch_means"))):
        fs.cfg = c
        R.render_reference(fs)                  # compiled first: both are timed warm
        t0 = time.perf_counter()
        with counted(fs) as n:
            ref = R.render_reference(fs)
        out[name] = {"seconds": time.perf_counter() - t0, "launches": n["launches"], "set_time_calls": n["moves"],
                     "set_time_ms": 1e3 * n["move_s"], "times": ref["ref_time_slices"]}
    fs.cfg = cfg
    out["split"] = _host_and_kernel(fs)
    fs.set_time(0.0)
    del fs
    _collect()
    return out


def gpu_projection(split: dict, samples: int) -> dict:
    """The host share of a reference on a GPU: host seconds as measured here, kernel seconds at the CUDA
    rates of :data:`GPU_MSAMPLES_PER_S` (low and high)."""
    out = {}
    for rate in GPU_MSAMPLES_PER_S:
        k = samples / (rate * 1e6)
        out[f"{rate:g}"] = {"kernel_s": k, "host_share": split["host_s"] / (split["host_s"] + k)}
    return out


def z_section(spec, cfg) -> dict:
    """The z tests on ``spec`` (moving) and on it with the shutter closed (static)."""
    from pipeline import render as R
    out = {}
    for name, sp in (("static", dataclasses.replace(spec, shutter=0.0)), ("moving", spec)):
        fs = R.FrameScene(sp, 0, cfg)
        a = R.render_reference(fs)
        fs.cfg = dataclasses.replace(cfg, seed_offset=1)
        b = R.render_reference(fs)
        out[name] = z_figures(z_scores(a, b))
        if name == "moving":
            fs.cfg = dataclasses.replace(cfg, seed_offset=2, ref_passes=2, ref_min_passes=2,
                                         ref_times=min(256, cfg.ref_spp // 4), ref_target_rel_stderr=None)
            dense = R.render_reference(fs)
            out["moving_vs_dense"] = {**z_figures(z_scores(a, dense)), "times": a["ref_time_slices"],
                                      "dense_times": dense["ref_time_slices"]}
        fs.cfg = cfg
        fs.set_time(0.0)
        del fs
        _collect()
    return out


def run(*, res: int = 64, ref_spp: int = 1024, scene_gen: dict | None = None) -> dict:
    """Print and return the reference figures."""
    from pipeline import render as R
    cfg = R.RenderConfig(res=(res, res), spp=8, layer_levels=0, ref_spp=ref_spp, ref_passes=32 if ref_spp >= 512 else 8,
                         ref_min_passes=16 if ref_spp >= 512 else 4)
    frames = bench_frames(res=res, scene_gen=scene_gen)
    rows = []
    print(f"  references of the end-to-end bench's frames, {res}x{res}, {ref_spp} spp, warm kernels:", flush=True)
    for label, spec in frames:
        f = frame_figures(spec, cfg)
        m, b, s = f["moments"], f["batch_means"], f["split"]
        f["gpu"] = gpu_projection(s, res * res * ref_spp)
        rows.append({"frame": label, **f})
        print(f"  {label:14s} {'moving' if f['has_motion'] else 'static'} ({f['displacement_px']:.2f} px a shutter): "
              f"moments {m['times']} time(s), {m['launches']} launches, {m['seconds']:.2f} s, set_time "
              f"{m['set_time_calls']}x {m['set_time_ms']:.0f} ms | batch_means {b['launches']} launches, "
              f"{b['seconds']:.2f} s, set_time {b['set_time_calls']}x {b['set_time_ms']:.0f} ms", flush=True)
        print(f"  {'':14s} host {1e3 * s['host_s']:.0f} ms (code generation {1e3 * s['codegen_s']:.0f}, set_time "
              f"{1e3 * s['set_time_s']:.0f}) against kernels {1e3 * s['kernel_s']:.0f} ms: host share "
              f"{s['host_s'] / max(s['wall_s'], 1e-9):.2f} here, on a GPU "
              + " to ".join(f"{g['host_share']:.2f}" for g in f["gpu"].values())
              + f" (kernels at {' to '.join(map(str, GPU_MSAMPLES_PER_S))} Msamples/s)", flush=True)
    moving = [r for r in rows if r["has_motion"]]
    static = [r for r in rows if not r["has_motion"]]
    out = {"frames": rows,
           "moving_launches_max": max((r["moments"]["launches"] for r in moving), default=0),
           "static_launches_max": max((r["moments"]["launches"] for r in static), default=0),
           "moments_s": sum(r["moments"]["seconds"] for r in rows),
           "batch_means_s": sum(r["batch_means"]["seconds"] for r in rows)}
    print(f"  launches: moving at most {out['moving_launches_max']} (target <= 16), static at most "
          f"{out['static_launches_max']} (target <= 2); the four references {out['moments_s']:.1f} s against "
          f"{out['batch_means_s']:.1f} s before", flush=True)
    pick = next((sp for label, sp in frames if moving and label == moving[0]["frame"]), frames[0][1])
    z = out["z"] = z_section(pick, cfg)
    for name, v in z.items():
        print(f"  z test {name:15s}: std {v['std']:.3f} (target {Z_STD[0]}-{Z_STD[1]}), |z| > 3 {100 * v['tail']:.2f}% "
              f"(target < {100 * Z_TAIL:g}%) of {v['values']}: {'pass' if v['pass'] else 'FAIL'}", flush=True)
    return out


if __name__ == "__main__":
    run()
