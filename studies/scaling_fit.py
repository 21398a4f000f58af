"""The scaling fit: a metric against the number of training frames, ``error(N) = a N^(-b) + c``.

numpy and scipy only. A *point* is one trained run: its training frames ``n``, its seed and its
per-frame values of one metric on the held-out frames (every run on the same frames, in the same
order); ``clips`` gives each held-out frame's clip, the unit a bootstrap resamples (a still is a clip
of one frame, as in :mod:`training.stats`).

* :func:`fit_power_law`: least squares of ``y = c + s a N^(-b)`` over the points' means, ``s = +1`` for
  a metric where lower is better (relMSE: ``c`` is the floor that more data cannot lower) and ``-1``
  where higher is better (PSNR: ``c`` is the ceiling). ``a >= 0``, ``0 <= b <= B_MAX``, and an error's
  floor ``c >= 0``. For each ``b`` the model is linear in ``(a, c)``; a grid over ``b`` with that linear
  solve gives the start of ``scipy.optimize.least_squares``, so no start value is guessed.
* :func:`bootstrap_fit`: the fit with 95% intervals on ``a``, ``b`` and ``c``: each resample draws the
  held-out clips with replacement (one draw for every run, so runs stay paired) and, for each
  training-set size, that size's seeds with replacement, then fits again. The intervals hold both the
  held-out frames' and the seeds' spread.
* :func:`support`: whether the points support a fit at all: at least three sizes, and the largest set
  shown better than the smallest by a paired per-frame difference (seeds averaged per frame, a bootstrap
  over clips, :func:`training.stats.paired_difference`). Otherwise the fit is reported but not used.
* :func:`frames_for_target`: the smallest ``N`` the fit predicts reaches a target, with the interval of
  that ``N`` over the resamples; :class:`~training.errors.TargetBelowFloorError` where the target is at
  or beyond the fitted floor (ceiling), naming it.
"""
from __future__ import annotations

import math

import numpy as np

from training import stats
from training.errors import ConfigError, TargetBelowFloorError

B_MAX = 4.0
B_GRID = np.linspace(0.0, B_MAX, 81)
LOWER_IS_BETTER = {"relmse": True, "smape": True, "flip": True, "psnr": False, "ssim": False, "tpsnr": False}


def sign_of(metric: str) -> int:
    """+1 where lower is better (an error falling to a floor), -1 where higher is better (rising to a ceiling)."""
    if metric not in LOWER_IS_BETTER:
        raise ConfigError(f"metric {metric!r} has no known direction; one of {sorted(LOWER_IS_BETTER)}")
    return 1 if LOWER_IS_BETTER[metric] else -1


def limit_name(metric: str) -> str:
    return "floor" if sign_of(metric) > 0 else "ceiling"


def power_law(n, a: float, b: float, c: float, sign: int = 1):
    """``c + sign * a * n^(-b)`` (float64)."""
    return c + sign * a * np.power(np.asarray(n, np.float64), -b)


def _linear(x: np.ndarray, y: np.ndarray, sign: int, floor0: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every ``b`` of :data:`B_GRID`: ``(A, c, rss)`` minimising ``sum (c + sign A x^-b - y)^2`` with
    ``A >= 0`` (and ``c >= 0`` when ``floor0``); ``x`` is N scaled to the largest N. Closed form: the
    unconstrained solve, else the best solution on a bound."""
    g = sign * np.power(x[None, :], -B_GRID[:, None])                    # (B, m)
    gm, ym = g.mean(axis=1), y.mean()
    var = ((g - gm[:, None]) ** 2).sum(axis=1)
    A = np.where(var > 1e-12, ((g - gm[:, None]) * (y - ym)).sum(axis=1) / np.maximum(var, 1e-300), 0.0)
    c = ym - A * gm
    bad = (A < 0) | (floor0 & (c < 0))
    cands = [(A, c, bad), (np.zeros_like(A), np.full_like(A, ym), np.full(A.shape, floor0 and ym < 0))]
    if floor0:                                                   # c on its bound 0
        gg = (g * g).sum(axis=1)
        cands.append((np.maximum(0.0, (g @ y) / np.maximum(gg, 1e-300)), np.zeros_like(A), np.zeros(A.shape, bool)))
    best_A, best_c, best = A.copy(), c.copy(), np.full(A.shape, np.inf)
    for a_, c_, no in cands:
        rss = np.where(no, np.inf, ((c_[:, None] + a_[:, None] * g - y) ** 2).sum(axis=1))
        take = rss < best
        best_A, best_c, best = np.where(take, a_, best_A), np.where(take, c_, best_c), np.minimum(rss, best)
    return best_A, best_c, best


def fit_power_law(n, y, sign: int = 1, floor0: bool | None = None) -> dict | None:
    """Least-squares fit of ``y = c + sign a n^(-b)`` (module docstring); ``{"a", "b", "c", "rss"}`` with
    ``a`` for ``n`` in frames, or None with fewer than three distinct ``n`` (or non-finite values).
    ``floor0``: bound ``c >= 0`` (default: for errors, ``sign`` +1)."""
    from scipy.optimize import least_squares
    n, y = np.asarray(n, np.float64), np.asarray(y, np.float64)
    if len(np.unique(n)) < 3 or not (np.isfinite(n).all() and np.isfinite(y).all()) or (n <= 0).any():
        return None
    floor0 = sign > 0 if floor0 is None else floor0
    top = float(n.max())
    x = n / top
    As, cs, rss = _linear(x, y, sign, floor0)
    j = int(np.argmin(rss))
    A, b0, c = float(As[j]), float(B_GRID[j]), float(cs[j])
    scale = max(float(np.abs(y).max()), 1e-12)
    res = least_squares(lambda p: (p[2] + sign * p[0] * np.power(x, -p[1]) - y) / scale,
                        x0=[A, min(max(b0, 1e-6), B_MAX - 1e-6), c],
                        bounds=([0.0, 0.0, 0.0 if floor0 else -np.inf], [np.inf, B_MAX, np.inf]), method="trf")
    A, b, c = (float(v) for v in res.x)
    rss = float(((power_law(x, A, b, c, sign) - y) ** 2).sum())
    return {"a": A * top ** b, "b": b, "c": c, "rss": rss}


# --------------------------------------------------------------------------------------------
# Points, their means and the bootstrap


def _matrix(points: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(n (R,), seeds (R,), values (R, F))`` of the points (every run on the same F frames)."""
    values = np.stack([np.asarray(p["values"], np.float64) for p in points])
    return (np.array([p["n"] for p in points], np.float64), np.array([p["seed"] for p in points]), values)


def by_size(points: list[dict]) -> dict[int, list[int]]:
    """Training-set size -> indices of its points, sizes ascending."""
    out: dict[int, list[int]] = {}
    for i, p in enumerate(points):
        out.setdefault(int(p["n"]), []).append(i)
    return dict(sorted(out.items()))


def size_table(points: list[dict], clips) -> list[dict]:
    """One row a size: ``n``, ``seeds``, ``mean`` (over seeds of each run's mean), ``seed_min``/``seed_max``
    (the runs' means), ``ci95`` (of the seeds-averaged per-frame values, a bootstrap over clips) and
    ``per_frame`` (those values, for paired differences)."""
    _, _, V = _matrix(points)
    rows = []
    for n, idx in by_size(points).items():
        means = V[idx].mean(axis=1)
        avg = V[idx].mean(axis=0)
        rows.append({"n": n, "seeds": [points[i]["seed"] for i in idx], "mean": float(means.mean()),
                     "seed_min": float(means.min()), "seed_max": float(means.max()),
                     "ci95": stats.mean_ci(avg, clips), "per_frame": avg})
    return rows


def paired(rows_a: dict, rows_b: dict, clips) -> dict | None:
    """Paired difference ``b - a`` of two :func:`size_table` rows over the frames (bootstrap over clips)."""
    ids = range(len(clips))
    return stats.paired_difference(dict(zip(ids, rows_a["per_frame"])), dict(zip(ids, rows_b["per_frame"])),
                                   dict(zip(ids, clips)))


def support(points: list[dict], clips, sign: int) -> dict:
    """Whether the points support a fit (module docstring): ``{"supported", "reason", "difference"}``,
    ``difference`` the paired difference largest minus smallest set."""
    rows = size_table(points, clips)
    if len(rows) < 3:
        return {"supported": False, "difference": None,
                "reason": f"{len(rows)} training-set size(s): a curve of three parameters needs at least three"}
    d = paired(rows[0], rows[-1], clips)
    n0, n1 = rows[0]["n"], rows[-1]["n"]
    if d is None or d["ci95"] is None:
        return {"supported": False, "difference": d, "reason": "no interval for the difference between the "
                                                              f"smallest and largest set ({n0} and {n1} frames)"}
    if not d["shown"]:
        return {"supported": False, "difference": d,
                "reason": f"the largest set ({n1} frames) is not shown to differ from the smallest ({n0}): the "
                          f"paired difference {d['mean']:+.4g} [{d['ci95'][0]:+.4g}, {d['ci95'][1]:+.4g}] holds 0"}
    if d["mean"] * sign > 0:
        return {"supported": False, "difference": d,
                "reason": f"the largest set ({n1} frames) is shown worse than the smallest ({n0}): "
                          f"{d['mean']:+.4g} [{d['ci95'][0]:+.4g}, {d['ci95'][1]:+.4g}]"}
    return {"supported": True, "difference": d, "reason": ""}


def _resample_means(V: np.ndarray, clips, resamples: int, rng) -> np.ndarray:
    """Every run's mean over each resample of the clips (R_s, runs), one clip draw shared by all runs."""
    _, inv = np.unique(np.asarray(clips), return_inverse=True)
    k = inv.max() + 1
    draws = rng.integers(0, k, size=(resamples, k))
    mult = np.stack([np.bincount(d, minlength=k) for d in draws]).astype(np.float64)    # (R_s, clips)
    w = mult[:, inv]                                                                     # (R_s, F)
    return (w @ V.T) / w.sum(axis=1, keepdims=True)


def bootstrap_fit(points: list[dict], clips, sign: int, resamples: int = 1000, seed: int = stats.SEED,
                  level: float = stats.LEVEL) -> dict | None:
    """:func:`fit_power_law` on the points' means with ``level`` intervals of ``a``, ``b``, ``c`` from
    ``resamples`` bootstrap fits (module docstring). ``{"a", "b", "c", "ci95": {"a", "b", "c"},
    "resamples", "failed", "samples": (R, 3) array of (a, b, c)}``; None where no fit is possible."""
    n, _, V = _matrix(points)
    if not np.isfinite(V).all():
        return None
    fit = fit_power_law(n, V.mean(axis=1), sign)
    if fit is None:
        return None
    rng = np.random.default_rng(seed)
    groups = list(by_size(points).values())
    means = _resample_means(V, clips, resamples, rng)
    samples = []
    for r in range(resamples):
        pick = np.concatenate([rng.choice(g, size=len(g), replace=True) for g in groups])
        f = fit_power_law(n[pick], means[r, pick], sign)
        if f is not None:
            samples.append((f["a"], f["b"], f["c"]))
    samples = np.array(samples, np.float64).reshape(-1, 3)
    lo, hi = (1 - level) / 2, 1 - (1 - level) / 2
    ci = {k: [float(np.quantile(samples[:, j], lo)), float(np.quantile(samples[:, j], hi))] if len(samples) else None
          for j, k in enumerate("abc")}
    return {**fit, "ci95": ci, "resamples": resamples, "failed": resamples - len(samples), "samples": samples}


# --------------------------------------------------------------------------------------------
# The frames a target needs


def frames_needed(a: float, b: float, c: float, target: float, sign: int) -> float:
    """``N`` with ``c + sign a N^(-b) = target``: ``inf`` where the target is at or beyond ``c`` (or the
    curve is flat), at least 0."""
    gap = sign * (target - c)
    if gap <= 0:
        return math.inf
    if a <= 0:
        return 0.0                          # a flat curve already at the target
    if b <= 0:
        return 0.0 if gap >= a else math.inf
    return float((a / gap) ** (1.0 / b))


def frames_for_target(fit: dict, target: float, metric: str, level: float = stats.LEVEL) -> dict:
    """The smallest number of training frames the fit (:func:`bootstrap_fit`) predicts reaches ``target``
    of ``metric``, with its ``level`` interval over the resamples (``inf`` at the top: in that share of
    the resamples the target lies beyond their floor, ``unreachable_share``). Raises
    :class:`TargetBelowFloorError` naming the floor (ceiling) and its interval when the fitted curve
    cannot reach the target."""
    sign = sign_of(metric)
    name = limit_name(metric)
    ci = fit["ci95"].get("c")
    if sign * (target - fit["c"]) <= 0:
        where = "below" if sign > 0 else "above"
        raise TargetBelowFloorError(
            f"{metric} target {target:g} is {where} the fitted {name} {fit['c']:.4g}"
            + (f" (95% interval [{ci[0]:.4g}, {ci[1]:.4g}])" if ci else "")
            + ": no number of frames reaches it on this curve; more of this data cannot get there at this budget")
    n = frames_needed(fit["a"], fit["b"], fit["c"], target, sign)
    per = np.array([frames_needed(a, b, c, target, sign) for a, b, c in fit["samples"]])
    lo, hi = (1 - level) / 2, 1 - (1 - level) / 2
    interval = [float(np.quantile(per, lo)), float(np.quantile(per, hi))] if per.size else None
    return {"metric": metric, "target": float(target), "frames": n, "ci95": interval,
            "unreachable_share": float(np.isinf(per).mean()) if per.size else None,
            name: fit["c"], f"{name}_ci95": ci}
