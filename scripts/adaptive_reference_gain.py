"""Would a per-pixel adaptive reference give more per sample than uniform passes? (issue 13)

    .venv/bin/python scripts/adaptive_reference_gain.py STORE [STORE ...]

For every complete frame of each store it reads the reference and its batch-means standard error,
turns them into each pixel's variance per sample (``stderr**2 * spp``, Rec. 709 luminance) and asks how
far the same number of samples, spread over the pixels differently, would lower the two error figures
the project uses:

- the relative standard error of the early stop (``pipeline.render.rel_stderr``: mean over pixels of
  ``stderr_Y / (mean_Y + 0.01)``): the best allocation gives pixel p samples in proportion to
  ``a_p ** (2/3)``, ``a_p = sigma_p / (mean_p + 0.01)``;
- the relMSE floor (``training.evaluate.reference_limits``: mean of ``stderr**2 / (mean**2 + 0.01)``):
  samples in proportion to ``sqrt(b_p)``, ``b_p = sigma_p**2 / (mean_p**2 + 0.01)``.

Two allocations: the ideal one, and the practical one (every pixel keeps the uniform first half of
the passes, as the early stop's minimum, and the second half goes only where it helps most). The figure
printed is the sample saving at equal error: ``1 - (E_adaptive / E_uniform)**2`` for the stderr figure
(error ~ 1/sqrt(n)) and ``1 - E_adaptive / E_uniform`` for relMSE (error ~ 1/n). Also the share of the
error held by the worst 1% and 10% of pixels. Pixel costs are taken as equal (path lengths differ).
"""
from __future__ import annotations

import sys

import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722])
EPS = 0.01


def _waterfill(w: np.ndarray, total: float, floor: np.ndarray) -> np.ndarray:
    """n >= floor with sum n = total, n proportional to w where above the floor (bisection on the scale)."""
    lo, hi = 0.0, total / max(w.sum(), 1e-30) * 4 + 1.0
    for _ in range(100):
        k = 0.5 * (lo + hi)
        s = np.maximum(floor, k * w).sum()
        lo, hi = (k, hi) if s < total else (lo, k)
    return np.maximum(floor, lo * w)


def frame_gain(mean: np.ndarray, stderr: np.ndarray, spp: int) -> dict:
    m = np.abs(mean @ LUMA).ravel()
    s = (stderr @ LUMA).ravel()
    var = s ** 2 * spp                            # per-sample variance of each pixel's luminance
    a = np.sqrt(var) / (m + EPS)                  # rel. stderr of pixel p is a / sqrt(n_p)
    b = var / (m ** 2 + EPS)                      # relMSE floor of pixel p is b / n_p
    P = len(m)
    N = spp * P
    uni_rel = np.mean(a / np.sqrt(spp))
    uni_mse = np.mean(b / spp)
    out = {}
    for name, floor in (("ideal", np.zeros(P)), ("half-uniform", np.full(P, spp / 2.0))):
        n_rel = _waterfill(a ** (2 / 3), N, floor)
        n_mse = _waterfill(np.sqrt(b), N, floor)
        out[f"{name}_rel_saving"] = 1 - (np.mean(a / np.sqrt(np.maximum(n_rel, 1e-9))) / uni_rel) ** 2
        out[f"{name}_mse_saving"] = 1 - np.mean(b / np.maximum(n_mse, 1e-9)) / uni_mse
    e = np.sort(a)[::-1]
    out["top1_share"] = e[:max(1, P // 100)].sum() / max(e.sum(), 1e-30)
    out["top10_share"] = e[:max(1, P // 10)].sum() / max(e.sum(), 1e-30)
    out["rel_stderr"] = uni_rel
    return out


def main(paths: list[str]) -> int:
    import zarr
    for path in paths:
        g = zarr.open_group(path, mode="r")
        done = np.asarray(g["status/complete"][:], bool)
        spps = np.asarray(g["frames/reference_spp"][:])
        rows = []
        for i in np.flatnonzero(done):                             # stored (frame, rgb, y, x)
            mean = np.moveaxis(np.asarray(g["reference/radiance"][i], np.float64), 0, -1)
            err = np.moveaxis(np.asarray(g["reference/stderr"][i], np.float64), 0, -1)
            rows.append(frame_gain(mean, err, int(spps[i])))
        keys = rows[0].keys()
        q = {k: np.percentile([rw[k] for rw in rows], [10, 50, 90]) for k in keys}
        print(f"{path}: {len(rows)} frames; 10/50/90th percentile over frames")
        for k in keys:
            print(f"  {k:<26} " + " / ".join(f"{v:.3f}" for v in q[k]))
        print(f"  {'mean':<26} " + ", ".join(f"{k} {np.mean([rw[k] for rw in rows]):.3f}" for k in keys if "saving" in k))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
