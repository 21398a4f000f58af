"""Renderer benchmark (``python -m pipeline bench --only render``): figures, not a timed test.

On one generated scene, in one process, with JIT kernels warmed up first:

- samples/s of the per-sample input loop (``pipeline.render.render_inputs``: radiance + 17 features)
  and of plain ``mi.render`` (path integrator, same scene, same spp); their ratio (target >= 0.7);
- samples/s of the reference path (``render_reference``: passes of the production size, 128 spp,
  + batch-means standard error) and of one ``mi.render`` call with the same total spp; their ratio
  (target >= 0.9);
- peak resident memory of a child process that renders one whole 256x256x8 frame (inputs, layers,
  a small reference) with ``render_frame`` (target < 4 GiB).

Throughput is measured at ``res`` (default 128x128: the ratios do not depend on it, the machine is
shared) as the best of ``repeats`` alternating runs of ours and ``mi.render``.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import time

import numpy as np

TARGET_INPUT_RATIO = 0.7
TARGET_REFERENCE_RATIO = 0.9
TARGET_PEAK_GIB = 4.0

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


def run(*, seed: int = 0, kind: str = "indoor", res: int = 128, spp: int = 8, ref_passes: int = 4,
        ref_pass_spp: int = 128, repeats: int = 3, memory: bool = True, memory_res: int = 256) -> dict:
    """Print and return the renderer's figures (dict of floats). ``memory_res``: the edge of the frame
    whose peak memory is measured in a child process (256 for the target; the tests use a tiny one)."""
    from pipeline import render as R
    from scene_gen.sampling import sample_scene

    spec = sample_scene(seed, kind, num_frames=1, res=res)
    # the reference with its production pass size (4096 spp in 32 passes = 128 spp a pass), fewer passes
    ref_spp = ref_passes * ref_pass_spp
    cfg = R.RenderConfig(res=(res, res), spp=spp, ref_spp=ref_spp, ref_passes=ref_passes,
                         ref_min_passes=min(16, ref_passes), layer_levels=0)
    # the benchmark measures one static pass: motion slicing is a scene property, not loop speed
    spec = dataclasses.replace(spec, shutter=0.0) if spec.has_motion else spec
    fs = R.FrameScene(spec, 0, cfg)
    mi = fs.mi
    n_in = res * res * spp
    n_ref = res * res * ref_spp

    def mi_render(k):
        np.asarray(mi.render(fs.scene, spp=k, seed=12345))

    t0 = time.perf_counter()
    R.render_inputs(fs)            # warm-up: compile the kernels once
    mi_render(spp)
    mi_render(ref_pass_spp)
    warm = time.perf_counter() - t0
    t_in, t_mi = _best_pair(lambda: R.render_inputs(fs), lambda: mi_render(spp), repeats)
    t_ref, t_mi_ref = _best_pair(lambda: R.render_reference(fs), lambda: mi_render(ref_spp), max(1, repeats - 1))
    out = {
        "scene": f"{kind} seed {seed}, {len(spec.objects)} objects, {res}x{res}",
        "threads": int(fs.dr.thread_count()),
        "warmup_seconds": warm,
        "inputs_msamples_per_s": n_in / t_in / 1e6,
        "mi_render_msamples_per_s": n_in / t_mi / 1e6,
        "inputs_ratio": t_mi / t_in,
        "reference_msamples_per_s": n_ref / t_ref / 1e6,
        "mi_render_reference_msamples_per_s": n_ref / t_mi_ref / 1e6,
        "reference_ratio": t_mi_ref / t_ref,
    }
    if memory:
        env = dict(os.environ)
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        r = subprocess.run([sys.executable, "-c", _CHILD, str(seed), kind, str(memory_res), "8"],
                           capture_output=True, text=True, env=env, cwd=root)
        tag = f"frame_{memory_res}x{memory_res}x8"
        if r.returncode == 0:
            child = json.loads(r.stdout.strip().splitlines()[-1])
            out.update({f"{tag}_seconds": child["seconds"], f"{tag}_peak_gib": child["peak_rss_gib"]})
        else:
            raise RuntimeError(f"the {memory_res}x{memory_res} memory child failed: "
                               + "\n".join((r.stderr or "").strip().splitlines()[-5:]))
    print(f"renderer on {out['scene']} ({out['threads']} threads, warm-up {warm:.1f} s):")
    print(f"  input loop  {out['inputs_msamples_per_s']:.2f} Msamples/s vs mi.render "
          f"{out['mi_render_msamples_per_s']:.2f}: ratio {out['inputs_ratio']:.2f} (target >= {TARGET_INPUT_RATIO})")
    print(f"  reference   {out['reference_msamples_per_s']:.2f} Msamples/s vs mi.render "
          f"{out['mi_render_reference_msamples_per_s']:.2f}: ratio {out['reference_ratio']:.2f} "
          f"(target >= {TARGET_REFERENCE_RATIO})")
    tag = f"frame_{memory_res}x{memory_res}x8"
    if f"{tag}_peak_gib" in out:
        print(f"  {memory_res}x{memory_res}x8 frame: peak memory {out[tag + '_peak_gib']:.2f} GiB "
              f"(target < {TARGET_PEAK_GIB} at 256x256), {out[tag + '_seconds']:.1f} s")
    return out


if __name__ == "__main__":
    run()
