"""Is a reference that stops at 3% relative standard error good enough to train on? (issue 13)

    .venv/bin/python scripts/reference_check.py [--steps 2000] [--seeds 0 1] [--out data/refcheck]

Renders train-cpu's 28 scenes twice at 32x32 with identical inputs and layers: once with the shipped
reference rule (at most 4096 spp in 32 passes, stopping after >= 16 once the relative standard error is
<= 3%) and once with a reference 4x longer than that cap (16384 spp in 128 passes, no early stop), plus
eval-cpu's 16 held-out scenes at 32x32 with full 4096-spp references to judge on. It trains ``nbg`` on each
training store with every seed (same steps, crops and seed for both stores), evaluates every run on the
held-out store, and prints the mean figures, the paired difference between the two references (same
seed, per frame) and the seed-to-seed difference (same reference), which is the noise to compare with.

Everything lands under ``--out`` (git-ignored data). Wall time on 2 cores: about 45 minutes.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
PY = sys.executable

SHORT = {"spp": 8, "layer_levels": 6, "ref_spp": 4096, "ref_passes": 32, "ref_min_passes": 16,
         "ref_target_rel_stderr": 0.03, "time_slices": 4}
LONG = {**SHORT, "ref_spp": 16384, "ref_passes": 128, "ref_min_passes": 128, "ref_target_rel_stderr": None}
EVAL = {**SHORT, "ref_target_rel_stderr": None}              # full 4096-spp references to judge on


def config(name: str, base: str, render: dict) -> dict:
    d = yaml.safe_load((ROOT / "configs" / base).read_text())
    d.update(name=name, resolution=[32, 32], render={k: v for k, v in render.items() if v is not None})
    return d


def run(cmd: list[str], **kw) -> None:
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, **kw)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(ROOT / "data" / "refcheck"))
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--model", default="nbg")
    a = p.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    stores = {}
    for name, base, render in (("short", "train-cpu.yaml", SHORT), ("long", "train-cpu.yaml", LONG),
                               ("eval", "eval-cpu.yaml", EVAL)):
        cfg = out / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump(config(f"refcheck-{name}", base, render)))
        stores[name] = out / f"{name}.zarr"
        run([PY, "-m", "pipeline", "dataset", "--config", str(cfg), "--out", str(stores[name]), "--no-progress"])
    # two trainings at a time, one thread each (two threads each on 2 cores oversubscribe)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    jobs = [(ref, seed) for seed in a.seeds for ref in ("short", "long")]
    for i in range(0, len(jobs), 2):
        procs = []
        for ref, seed in jobs[i:i + 2]:
            cmd = [PY, "-m", "training", "train", "--model", a.model, "--store", str(stores[ref]), "--steps",
                   str(a.steps), "--crop", "32", "--seed", str(seed), "--workers", "0", "--no-progress",
                   "--out", str(out / "runs" / f"{ref}-{seed}")]
            print("$", " ".join(cmd), flush=True)
            procs.append(subprocess.Popen(cmd, cwd=ROOT, env=env))
        if any(pr.wait() for pr in procs):
            raise SystemExit("a training run failed")
    res = {}
    for ref, seed in jobs:
        js = out / "runs" / f"{ref}-{seed}" / "eval.json"
        run([PY, "-m", "training", "evaluate", "--checkpoint", str(out / "runs" / f"{ref}-{seed}" / "checkpoint.pt"),
             "--store", str(stores["eval"]), "--out", str(js), "--no-flip"])
        res[(ref, seed)] = json.loads(js.read_text())
    report(res, a.seeds, stores)
    return 0


def _per_frame(r: dict, key: str) -> np.ndarray:
    return np.array([f[key] for f in r["frames"]], np.float64)


def report(res: dict, seeds: list[int], stores: dict) -> None:
    import zarr
    for name in ("short", "long"):
        g = zarr.open_group(str(stores[name]), mode="r")
        spp = np.asarray(g["frames/reference_spp"][:])
        rel = np.asarray(g["frames/reference_rel_stderr"][:])
        print(f"{name} references: spp {int(spp.min())}-{int(spp.max())} (mean {spp.mean():.0f}; "
              f"{int((spp < spp.max()).sum())} of {len(spp)} frames stopped early), rel. stderr median {np.median(rel):.4f}")
    keys = ("psnr", "relmse", "ssim")
    print("\nrun           " + "".join(f"{k:>10}" for k in keys))
    for (ref, seed), r in res.items():
        print(f"{ref + '-' + str(seed):<14}" + "".join(f"{r['mean'][k]:>10.4f}" for k in keys))
    for k in ("psnr", "ssim"):
        d_ref = [_per_frame(res[("long", s)], k) - _per_frame(res[("short", s)], k) for s in seeds]
        d_ref = np.concatenate(d_ref)
        print(f"\n{k}: long - short reference (paired, {len(d_ref)} frame-runs): mean {d_ref.mean():+.4f}, "
              f"standard error {d_ref.std(ddof=1) / np.sqrt(len(d_ref)):.4f}")
        if len(seeds) > 1:
            d_seed = np.concatenate([_per_frame(res[(ref, seeds[1])], k) - _per_frame(res[(ref, seeds[0])], k)
                                     for ref in ("short", "long")])
            print(f"{k}: seed {seeds[1]} - seed {seeds[0]} (same reference): mean {d_seed.mean():+.4f}, "
                  f"mean |difference| of the run means "
                  f"{np.mean([abs(res[(r, seeds[1])]['mean'][k] - res[(r, seeds[0])]['mean'][k]) for r in ('short', 'long')]):.4f}")


if __name__ == "__main__":
    raise SystemExit(main())
