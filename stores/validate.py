"""Store validator: schema, completeness, NaN/Inf counts, value ranges, reference standard error.

``validate_store(path) -> StoreReport``; ``main(argv)`` is ``python -m pipeline validate STORE``
(exit 0: no problem, 1: problems found, 2: not a readable store of this schema).

Per complete frame it checks: no NaN/Inf in any array; radiance, layers and reference >= 0;
reference standard error >= 0; features in range (albedo and roughness in [0, 1], time in [0, 1],
lens position inside the unit disk, depth >= 0, normals of unit length or 0 on a miss); guides the
same. It reports each frame's value ranges and the reference's mean relative standard error
(``stderr / max(reference, 1e-3)``) with the renderer's own figure (``frames/reference_rel_stderr``).
Incomplete frames are problems (with their recorded error text).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from stores.contract import FEATURE_GROUPS
from stores.errors import StoreError
from stores.reader import open_store
from stores.schema import ARRAYS

_TOL = 2e-3          # float16 features: rel. precision ~5e-4


@dataclass
class FrameReport:
    index: int
    complete: bool
    error: str = ""
    nonfinite: dict = field(default_factory=dict)        # array -> count of NaN/Inf
    ranges: dict = field(default_factory=dict)           # array -> [min, max] of finite values
    ref_rel_stderr: float | None = None                  # measured mean relative standard error
    ref_rel_stderr_meta: float | None = None             # the renderer's figure
    renderer_nonfinite: int = 0                          # NaN/Inf the renderer replaced (frames/nonfinite_*)
    problems: list = field(default_factory=list)


@dataclass
class StoreReport:
    path: str
    schema_version: int | None = None
    layout: dict = field(default_factory=dict)
    num_frames: int = 0
    frames: list = field(default_factory=list)
    problems: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and all(not f.problems for f in self.frames)

    @property
    def incomplete(self) -> list[int]:
        return [f.index for f in self.frames if not f.complete]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ok"] = self.ok
        d["incomplete"] = self.incomplete
        return d

    def format(self, verbose: bool = False) -> str:
        lines = [f"store {self.path}: schema v{self.schema_version}, {self.num_frames} frames, "
                 f"{self.layout.get('height')}x{self.layout.get('width')}, {self.layout.get('spp')} spp"]
        done = [f for f in self.frames if f.complete]
        lines.append(f"  complete {len(done)}/{len(self.frames)} checked; incomplete: {self.incomplete or 'none'}")
        rel = [f.ref_rel_stderr for f in done if f.ref_rel_stderr is not None]
        if rel:
            lines.append(f"  reference rel. stderr: mean {np.mean(rel):.4g}, median {np.median(rel):.4g}, "
                         f"max {np.max(rel):.4g} (frame {done[int(np.argmax(rel))].index})")
        replaced = sum(f.renderer_nonfinite for f in done)
        if replaced:
            lines.append(f"  NaN/Inf replaced by the renderer: {replaced} values in "
                         f"{sum(1 for f in done if f.renderer_nonfinite)} frame(s)")
        for p in self.problems:
            lines.append(f"  PROBLEM: {p}")
        for f in self.frames:
            if f.problems or verbose:
                status = "ok" if not f.problems else "; ".join(f.problems)
                rs = f"{f.ref_rel_stderr:.4g}" if f.ref_rel_stderr is not None else "-"
                lines.append(f"  frame {f.index:6d}: complete={f.complete} rel_stderr={rs} "
                             f"replaced_nonfinite={f.renderer_nonfinite} {status}")
                if verbose and f.ranges:
                    for k, (lo, hi) in f.ranges.items():
                        lines.append(f"      {k:18s} [{lo:.4g}, {hi:.4g}] nonfinite={f.nonfinite.get(k, 0)}")
        lines.append("OK" if self.ok else "PROBLEMS FOUND")
        return "\n".join(lines)


def _range_check(name, a, lo=None, hi=None, problems=None, tol=_TOL):
    fin = a[np.isfinite(a)]
    if fin.size == 0:
        return
    if lo is not None and fin.min() < lo - tol:
        problems.append(f"{name} below {lo}: min {fin.min():.4g}")
    if hi is not None and fin.max() > hi + tol:
        problems.append(f"{name} above {hi}: max {fin.max():.4g}")


def check_frame_values(fr: dict, report: FrameReport) -> None:
    """Fill ``report`` from one frame in the contract layout (``Store.read_frame``)."""
    p = report.problems
    for key, a in fr.items():
        if key == "meta":
            continue
        a = np.asarray(a)
        bad = int(a.size - np.isfinite(a).sum())
        report.nonfinite[key] = bad
        if bad:
            p.append(f"{key}: {bad} NaN/Inf values")
        fin = a[np.isfinite(a)]
        if fin.size:
            report.ranges[key] = [float(fin.min()), float(fin.max())]
    for key in ("radiance", "layers", "reference", "reference_stderr"):
        _range_check(key, fr[key], lo=0.0, problems=p, tol=0.0)
    f = fr["features"]
    g = FEATURE_GROUPS
    _range_check("features.albedo", f[..., g["albedo"]], 0.0, 1.0, p)
    _range_check("features.roughness", f[..., g["roughness"]], 0.0, 1.0, p)
    _range_check("features.time", f[..., g["time"]], 0.0, 1.0, p)
    _range_check("features.depth", f[..., g["depth"]], 0.0, None, p)
    lens = np.linalg.norm(f[..., g["lens"]], axis=-1)
    _range_check("features.lens radius", lens, None, 1.0, p)
    n = np.linalg.norm(f[..., g["normal"]], axis=-1)
    odd = np.isfinite(n) & (n > 1e-3) & (np.abs(n - 1) > 1e-2)
    if odd.any():
        p.append(f"features.normal: {int(odd.sum())} samples neither unit length nor 0")
    _range_check("guides_albedo", fr["guides_albedo"], 0.0, 1.0, p)
    _range_check("guides_depth", fr["guides_depth"], 0.0, None, p)
    _range_check("guides_normal", fr["guides_normal"], -1.0, 1.0, p, tol=1e-2)
    ref, se = fr["reference"].astype(np.float64), fr["reference_stderr"].astype(np.float64)
    if np.isfinite(ref).all() and np.isfinite(se).all():
        report.ref_rel_stderr = float(np.mean(se / np.maximum(np.abs(ref), 1e-3)))


def parse_frames(spec: str | None, num_frames: int) -> list[int]:
    """``'all'``/None, ``'3'``, ``'0,2,5-7'`` -> sorted frame indices (``ValueError`` if out of range)."""
    if spec is None or spec.strip().lower() in ("", "all"):
        return list(range(num_frames))
    out = set()
    for part in spec.split(","):
        part = part.strip()
        if "-" in part:
            a, b = (int(v) for v in part.split("-", 1))
            out.update(range(a, b + 1))
        else:
            out.add(int(part))
    bad = [i for i in out if not 0 <= i < num_frames]
    if bad:
        raise ValueError(f"frames {sorted(bad)} outside 0..{num_frames - 1}")
    return sorted(out)


def validate_store(path, frames=None) -> StoreReport:
    """Validate the store at ``path`` (all frames, or the indices in ``frames``). Raises StoreError
    subclasses when the path is not a readable store of this schema."""
    store = open_store(path)
    rep = StoreReport(path=str(path), schema_version=store.schema_version,
                      layout=store.layout.to_dict(), num_frames=store.num_frames)
    lay = store.layout
    for spec in ARRAYS:
        arr = store.root[spec.path]
        want = spec.shape(lay)
        if tuple(arr.shape) != want:
            rep.problems.append(f"{spec.path}: shape {tuple(arr.shape)}, layout says {want}")
        if tuple(arr.metadata.dimension_names or ()) != spec.dims:
            rep.problems.append(f"{spec.path}: dimension names {arr.metadata.dimension_names}, expected {spec.dims}")
    indices = range(store.num_frames) if frames is None else frames
    for i in indices:
        meta = store.frames_meta(i)
        fr_rep = FrameReport(index=i, complete=meta["complete"], error=meta["error"])
        if not meta["complete"]:
            fr_rep.problems.append("incomplete" + (f" (error: {meta['error']})" if meta["error"] else ""))
        else:
            fr_rep.ref_rel_stderr_meta = meta["reference_rel_stderr"]
            fr_rep.renderer_nonfinite = int(meta["nonfinite_inputs"] + meta["nonfinite_layers"]
                                            + meta["nonfinite_reference"])
            check_frame_values(store.read_frame(i, [k for k in _IMAGE_KEYS]), fr_rep)
        rep.frames.append(fr_rep)
    return rep


_IMAGE_KEYS = ("radiance", "features", "layers", "reference", "reference_stderr", "guides_albedo",
               "guides_normal", "guides_depth", "guides_motion", "camera_to_world", "world_to_clip")


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The ``validate`` sub-command's arguments (shared by ``python -m pipeline`` and ``python -m stores``)."""
    ap.add_argument("store", help="path of the Zarr store")
    ap.add_argument("--frames", default=None, help="frames to check: all (default), 3, 0,2,5-7")
    ap.add_argument("--json", action="store_true", help="print the report as JSON")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per frame with value ranges")


def run(args) -> int:
    """Validate and print; 0 if no problem, 1 if problems. Raises StoreError if the store cannot be read."""
    store = open_store(args.store)
    try:
        frames = parse_frames(args.frames, store.num_frames)
    except ValueError as e:
        raise StoreError(str(e)) from e
    rep = validate_store(args.store, frames)
    print(json.dumps(rep.to_dict(), indent=1) if args.json else rep.format(args.verbose))
    return 0 if rep.ok else 1


def cli_main(prog: str, description: str, add_args, run_fn, argv=None) -> int:
    """A stand-alone command (``python -m stores PROG``): parse, run, StoreError -> message and exit 2."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    add_args(ap)
    args = ap.parse_args(argv)
    try:
        return run_fn(args)
    except StoreError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def main(argv=None) -> int:
    """``validate STORE``: exit 0 (ok), 1 (problems found), 2 (not a readable store of this schema)."""
    return cli_main("validate", "Check a store: schema, completeness, NaN/Inf counts, value ranges and "
                    "reference standard error, per frame.", add_arguments, run, argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
