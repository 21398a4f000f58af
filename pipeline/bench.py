"""``python -m pipeline bench``: the benchmarks of rendering, the store, the scheduler and scale, figures
printed, one run. ``make bench`` runs it, then the models' (``python -m training bench --compile``:
training reads the stores, the pipeline never imports it).

Each area contributes ``run() -> dict`` in its own module; this collects them and prints a summary.
Speed and memory targets live here, not in timed tests.
"""
from __future__ import annotations

import importlib
import json
import time
import traceback

SUITES = {
    "render": "pipeline.bench_render",     # samples/s of the per-sample loop and reference vs mi.render, peak memory
    "reference": "pipeline.bench_reference",   # launches, host vs kernel ms, z tests of the reference
    "store": "stores.bench",               # crops/s and MB/s vs raw np.load, stored/raw bytes
    "dask": "pipeline.bench_dask",         # frames/min 1 vs 2 workers, scheduler overhead per task
    "scale": "pipeline.bench_scale",       # per-frame cost of every stage at 100, 1,000 and 10,000 frames
}
DEFAULT_SUITES = ("render", "reference", "store", "dask")   # `make bench` (then training's); scale runs alone (--only scale)


# `--tiny`: every suite at a size that runs in seconds (tests/test_pipeline_bench.py runs each one this way,
# so a benchmark cannot rot unseen); the figures are then meaningless.
TINY = {
    "render": {"res": 16, "ref_passes": 2, "ref_pass_spp": 8, "repeats": 1, "memory_res": 16, "e2e_res": 8,
               "e2e_warm": False, "e2e_ref_spp": 16, "fph_res": 8, "counts_res": 16, "scene_gen": {"indoor_objects": 4, "outdoor_objects": 6}},
    "reference": {"res": 8, "ref_spp": 64, "scene_gen": {"indoor_objects": 4, "outdoor_objects": 6}},
    "store": {"crops": 4, "crop": 16, "frames": 2, "size": 32},
    "dask": {"frames": 2, "res": 8, "ref_spp": 16, "objects": 3, "noop_tasks": 20},
    "scale": {"frames": (6, 12), "graphs": False},
}


def add_arguments(p) -> None:
    p.add_argument("--only", nargs="*", choices=sorted(SUITES),
                   help=f"run only these benchmark suites (default: {' '.join(DEFAULT_SUITES)}; scale takes "
                        "tens of minutes at 10,000 frames and runs only when named)")
    p.add_argument("--json", help="also write all figures to this JSON file (with --only scale alone: the scale "
                                  'table itself, {stage: {"F": per-frame value}})')
    p.add_argument("--frames", nargs="+", type=int, default=None,
                   help="scale: the dataset sizes to measure (default 100 1000 10000)")
    p.add_argument("--tiny", action="store_true",
                   help="every suite at a tiny size (seconds; checks that the benchmarks run, figures meaningless)")


def run(args) -> int:
    results, failed = {}, []
    for name, module in SUITES.items():
        if (args.only and name not in args.only) or (not args.only and name not in DEFAULT_SUITES):
            continue
        print(f"\n=== bench: {name} ({module}) ===", flush=True)
        t0 = time.perf_counter()
        try:
            kwargs = TINY.get(name, {}) if args.tiny else {}
            if name == "scale" and getattr(args, "frames", None):
                kwargs = {**kwargs, "frames": tuple(args.frames)}
            results[name] = importlib.import_module(module).run(**kwargs)
        except Exception:  # a broken suite is reported, the others still run
            traceback.print_exc()
            failed.append(name)
            continue
        print(f"--- {name} done in {time.perf_counter() - t0:.1f} s", flush=True)
    print("\n=== summary ===")
    print(json.dumps(results, indent=2, default=str))
    if args.json:
        only_scale = bool(args.only) and set(args.only) == {"scale"} and "scale" in results
        with open(args.json, "w") as f:
            json.dump(results["scale"] if only_scale else results, f, indent=2, default=str)
    if failed:
        print(f"failed suites: {', '.join(failed)}")
    return 1 if failed else 0
