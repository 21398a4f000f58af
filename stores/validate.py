"""Store validator: schema, completeness, NaN/Inf counts, value ranges, reference standard error.

``validate_store(path) -> StoreReport``; ``run(args)`` is ``python -m pipeline validate STORE``.
Exit codes (:data:`core.cli.EXIT_CODES`): 0 no problem; 1 problems found in readable data (incomplete frames, NaN/Inf,
values out of range, an all-zero reference); 2 not a readable store (no store, not ours, unknown schema
version, creation cut short, bad arguments); 3 the store is damaged (a complete frame's chunk file
missing, a truncated/garbage chunk or one failing its crc32c, array metadata that disagrees with the
schema). Damage is listed in full before exiting 3: every missing shard and every damaged or missing
``frames/*`` / ``status/*`` / camera-matrix chunk, each with its array, frame and file.

Array metadata (``zarr.json``: dtype, shape, chunks, codecs, fill value, dims) is compared with the
schema table first; if it disagrees no frame is read (its bytes would be misread).

Per complete frame it applies :mod:`stores.fitness`, the one check of a frame's fitness that
``train``, ``evaluate``, ``report``, ``hard-cases`` and ``export`` apply too: no NaN/Inf in any array;
radiance, layers and reference >= 0; reference standard error >= 0; features in range (albedo and
roughness in [0, 1], time in [0, 1], lens position inside the unit disk, depth >= 0, normals of unit
length or 0 on a miss); guides the same; bounds of 1 with the slack the store's rounding may add
(``compact2``'s 4-bit lens: 2**-5); no NaN/Inf the renderer replaced (``frames/nonfinite_*``), except
in a frame of the ``nan`` hard case, where it is a note. It reports each frame's value ranges and the reference's mean relative standard error
(``stderr / max(reference, 1e-3)``) with the renderer's own figure (``frames/reference_rel_stderr``).
Incomplete frames are problems (with their recorded error text). A complete frame whose reference
is all zero while its input radiance is not is a problem. Schema v1 stores skipped all-zero shards,
so a missing v1 shard is only a note ("read as zeros"), not damage.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from stores import create, schema
from core.cli import DAMAGED, OK, PROBLEMS
from stores.errors import MissingShardError, StoreCorruptionError, StoreError
from stores.fitness import FRAME_KEYS, check_values, renderer_findings
from stores.reader import open_store

@dataclass
class FrameReport:
    index: int
    complete: bool
    error: str = ""
    nonfinite: dict = field(default_factory=dict)        # array -> count of NaN/Inf
    ranges: dict = field(default_factory=dict)           # array -> [min, max] of finite values
    ref_rel_stderr: float | None = None                  # measured mean relative standard error
    ref_rel_stderr_meta: float | None = None             # the renderer's figure
    psnr_ceiling: float | None = None                    # dB: PSNR of the truth against this reference
    relmse_floor: float | None = None                    # relMSE of the truth against this reference
    renderer_nonfinite: int = 0                          # NaN/Inf the renderer replaced (frames/nonfinite_*)
    problems: list = field(default_factory=list)         # everything wrong (damage included)
    notes: list = field(default_factory=list)            # not problems (NaN its hard case intends)
    damage: list = field(default_factory=list)           # missing / corrupt files of this frame


@dataclass
class StoreReport:
    path: str
    schema_version: int | None = None
    layout: dict = field(default_factory=dict)
    num_frames: int = 0
    frames: list = field(default_factory=list)
    problems: list = field(default_factory=list)         # store-level (damage included)
    damage: list = field(default_factory=list)           # store-level damage (array metadata, metadata chunks)
    notes: list = field(default_factory=list)            # not problems (e.g. v1 all-zero shards)
    damaged_meta_frames: list = field(default_factory=list)   # frames whose frames/* or status chunk is damaged

    @property
    def ok(self) -> bool:
        return not self.problems and all(not f.problems for f in self.frames)

    @property
    def damaged(self) -> bool:
        return bool(self.damage) or any(f.damage for f in self.frames)

    @property
    def damaged_frames(self) -> list[int]:
        """Frames with damaged or missing files (re-render them: ``validate --mark-damaged``)."""
        return sorted({f.index for f in self.frames if f.damage} | set(self.damaged_meta_frames))

    @property
    def exit_code(self) -> int:
        return DAMAGED if self.damaged else OK if self.ok else PROBLEMS

    @property
    def incomplete(self) -> list[int]:
        return [f.index for f in self.frames if not f.complete]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ok"] = self.ok
        d["damaged"] = self.damaged
        d["incomplete"] = self.incomplete
        return d

    def format(self, verbose: bool = False) -> str:
        lines = [f"store {self.path}: schema v{self.schema_version}, {self.num_frames} frames, "
                 f"{self.layout.get('height')}x{self.layout.get('width')}, {self.layout.get('spp')} spp"]
        done = [f for f in self.frames if f.complete]
        lines.append(f"  complete {len(done)}/{len(self.frames)} checked; incomplete: {self.incomplete or 'none'}")
        rel = [f.ref_rel_stderr for f in done if f.ref_rel_stderr is not None]
        if rel:
            q = np.percentile(rel, [10, 50, 90])
            lines.append(f"  reference rel. stderr: mean {np.mean(rel):.4g}, 10/50/90 % {q[0]:.4g} / {q[1]:.4g} / "
                         f"{q[2]:.4g}, max {np.max(rel):.4g} (frame {done[int(np.argmax(rel))].index})")
        ceil = [f.psnr_ceiling for f in done if f.psnr_ceiling is not None and np.isfinite(f.psnr_ceiling)]
        if ceil:
            floor = [f.relmse_floor for f in done if f.relmse_floor is not None]
            lines.append(f"  reference error as a metric limit: PSNR ceiling (tone-mapped, eq. 7) median "
                         f"{np.median(ceil):.1f} dB, lowest {np.min(ceil):.1f} dB; relMSE floor median "
                         f"{np.median(floor):.3g}, highest {np.max(floor):.3g}: a denoiser scored against these "
                         "references cannot be told apart from the truth beyond them")
        replaced = sum(f.renderer_nonfinite for f in done)
        if replaced:
            lines.append(f"  NaN/Inf replaced by the renderer: {replaced} values in "
                         f"{sum(1 for f in done if f.renderer_nonfinite)} frame(s)")
        for n in self.notes:
            lines.append(f"  note: {n}")
        for p in self.problems:
            lines.append(f"  {'DAMAGE' if p in self.damage else 'PROBLEM'}: {p}")
        for f in self.frames:
            for n in f.notes:
                lines.append(f"  note: frame {f.index}: {n}")
            if f.problems or verbose:
                status = "ok" if not f.problems else "; ".join(f.problems)
                rs = f"{f.ref_rel_stderr:.4g}" if f.ref_rel_stderr is not None else "-"
                lines.append(f"  frame {f.index:6d}: complete={f.complete} rel_stderr={rs} "
                             f"replaced_nonfinite={f.renderer_nonfinite} {status}")
                if verbose and f.ranges:
                    for k, (lo, hi) in f.ranges.items():
                        lines.append(f"      {k:18s} [{lo:.4g}, {hi:.4g}] nonfinite={f.nonfinite.get(k, 0)}")
        if self.incomplete:
            failed = sum(1 for f in self.frames if not f.complete and any("error:" in p for p in f.problems))
            why = f", {failed} of them failed" if failed else ""
            lines.append(f"  {len(self.incomplete)} of {len(self.frames)} frames are incomplete (an interrupted or "
                         f"unfinished run{why}): the same `python -m pipeline dataset` command (same config and "
                         "--out) finishes them and keeps the complete ones; until then train and evaluate use "
                         "the complete frames only with --skip-bad-frames")
        lines.append("STORE DAMAGED" if self.damaged else "OK" if self.ok else "PROBLEMS FOUND")
        return "\n".join(lines)


def check_frame_values(fr: dict, report: FrameReport, layout=None) -> None:
    """Fill ``report`` from one frame in the contract layout (``Store.read_frame``) with
    :func:`stores.fitness.check_values` (the one value check every command uses)."""
    vc = check_values(fr, layout)
    report.problems.extend(vc.problems)
    report.nonfinite.update(vc.nonfinite)
    report.ranges.update(vc.ranges)
    report.ref_rel_stderr, report.psnr_ceiling, report.relmse_floor = vc.ref_rel_stderr, vc.psnr_ceiling, vc.relmse_floor


def parse_frames(spec: str | None, num_frames: int) -> list[int]:
    """``'all'``/None, ``'3'``, ``'0,2,5-7'`` -> sorted frame indices (``ValueError`` if out of range)."""
    if spec is None or spec.strip().lower() in ("", "all"):
        return list(range(num_frames))
    out = set()
    for part in spec.split(","):
        part = part.strip()
        if "-" in part:
            a, b = (int(v) for v in part.split("-", 1))
            if b < a:
                raise ValueError(f"frame range {part!r} is empty (write it low-high, e.g. {b}-{a})")
            out.update(range(a, b + 1))
        else:
            out.add(int(part))
    bad = [i for i in out if not 0 <= i < num_frames]
    if bad:
        raise ValueError(f"frames {sorted(bad)} outside 0..{num_frames - 1}")
    return sorted(out)


def validate_store(path, frames=None, *, read_values: bool = True) -> StoreReport:
    """Validate the store at ``path`` (all frames, or the indices in ``frames``). Raises StoreError
    subclasses when the path is not a readable store of a known schema; damage is reported, not raised
    (``report.damage``, ``FrameReport.damage``; ``report.exit_code`` 3): every damaged or missing
    metadata chunk and every missing shard is listed, each with its array, frame and file.
    ``read_values=False`` checks the array metadata, completeness, files and the renderer's counts
    but reads no image (a dataset run's summary: its write tasks checked the values they wrote)."""
    root, lay = schema.open_group(path, mode="r", check=False)
    rep = StoreReport(path=str(path), schema_version=schema.SCHEMA_VERSION, layout=lay.to_dict(),
                      num_frames=lay.num_frames)
    bad = schema.array_problems(root, lay)
    for p in bad:
        _damage(rep, f"array metadata: {p}")
    if bad:
        rep.problems.append("frames not checked: their arrays' metadata disagrees with the schema")
        return rep
    stale = _consolidation_note(path, root)
    if stale:
        rep.notes.append(stale)
    leftover = create.partial_files(path)
    if leftover:
        rep.notes.append(f"{len(leftover)} temporary file(s) of a write cut short ({', '.join(leftover[:3])}"
                         f"{', ...' if len(leftover) > 3 else ''}): not store data; the next `python -m pipeline "
                         "dataset` run on this store removes them")
    store = open_store(path, check=False)                  # array_problems ran above
    meta_damage = store.metadata_damage()                  # frame -> errors of its frames/* and status/* chunks
    indices = range(store.num_frames) if frames is None else frames
    rep.damaged_meta_frames = sorted(set(meta_damage) & {int(i) for i in indices})
    lost = store.missing_data(indices)
    for i in indices:
        fr_rep = FrameReport(index=i, complete=False)
        rep.frames.append(fr_rep)
        _check_frame(store, i, fr_rep, meta_damage.get(i, []), lost.get(i, []), read_values)
    return rep


def _damage(where, msg: str) -> None:
    where.problems.append(msg)
    where.damage.append(msg)


def _check_frame(store, i: int, fr_rep: FrameReport, meta_errors: list, lost: list, read_values: bool) -> None:
    """Frame ``i``'s report: its metadata damage and lost files (``meta_errors``, ``lost``: ``[(array,
    file)]``), completeness, the renderer's counts and (``read_values``) the values of every array."""
    missing = {f for _, f in lost}
    for e in meta_errors:                       # missing metadata chunks are listed with the shards below
        if not (isinstance(e, MissingShardError) and e.path in missing):
            _damage(fr_rep, str(e))
    for array, f in lost:
        _damage(fr_rep, f"{array}: frame {i} is complete but its chunk file {f} is missing")
    try:
        meta = store.frames_meta(i, scene=False)
    except StoreCorruptionError as e:           # a camera matrix, or the metadata damage listed above
        if not meta_errors and e.path not in missing:
            _damage(fr_rep, str(e))
        return
    fr_rep.complete, fr_rep.error = meta["complete"], meta["error"]
    if not meta["complete"]:
        fr_rep.problems.append("incomplete" + (f" (error: {meta['error']})" if meta["error"] else ""))
        return
    if fr_rep.damage:
        return
    fr_rep.ref_rel_stderr_meta = meta["reference_rel_stderr"]
    fr_rep.renderer_nonfinite = int(meta["nonfinite_inputs"] + meta["nonfinite_layers"] + meta["nonfinite_reference"])
    found, notes = renderer_findings(meta)       # stores.fitness: the one fitness check, as train sees it
    fr_rep.problems.extend(found)
    fr_rep.notes.extend(notes)
    if not read_values:
        return
    data = {}
    for key in FRAME_KEYS:
        try:
            data[key] = store.read_frame(i, [key])[key]
        except StoreCorruptionError as e:
            _damage(fr_rep, str(e))
    if not fr_rep.damage:
        check_frame_values(data, fr_rep, store.layout)


def _consolidation_note(path, root) -> str | None:
    """A note when a store's consolidated metadata (for xarray) is missing or out of date."""
    import os
    if not isinstance(path, (str, os.PathLike)) or "://" in os.fspath(path):
        return None
    try:
        with open(os.path.join(os.fspath(path), "zarr.json")) as f:
            cm = (json.load(f).get("consolidated_metadata") or {}).get("metadata") or {}
    except (OSError, ValueError):
        return None
    fix = f"stores.schema.consolidate({os.fspath(path)!r}) rewrites it"
    if not cm:
        return f"no consolidated metadata (xarray.open_zarr warns and reads slower); {fix}"
    have = tuple((cm.get("status/complete") or {}).get("shape", ()))
    if have != tuple(root["status/complete"].shape):
        return (f"consolidated metadata is out of date (status/complete {have} vs "
                f"{root['status/complete'].shape}); {fix}")
    return None


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The ``validate`` sub-command's arguments (shared by ``python -m pipeline`` and ``python -m stores``)."""
    ap.add_argument("store", help="path of the Zarr store")
    ap.add_argument("--frames", default=None, help="frames to check: all (default), 3, 0,2,5-7")
    ap.add_argument("--json", action="store_true", help="print the report as JSON")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per frame with value ranges")
    ap.add_argument("--mark-damaged", action="store_true",
                    help="mark every frame with damaged or missing files incomplete (status/error says why), "
                         "so the next `python -m pipeline dataset` run with the same config re-renders it")


def run(args) -> int:
    """Validate and print; returns the exit code (``core.cli``: 0 ok, 1 problems, 3 damaged). Raises
    StoreError (exit 2) if the path is not a readable store or the arguments are bad."""
    _, lay = schema.open_group(args.store, mode="r", check=False)
    try:
        frames = parse_frames(args.frames, lay.num_frames)     # the layout's count: no array is read here
    except ValueError as e:
        raise StoreError(f"--frames {args.frames}: {e}") from e
    rep = validate_store(args.store, frames)   # damage it could not take in: StoreCorruptionError, exit 3
    print(json.dumps(rep.to_dict(), indent=1) if args.json else rep.format(args.verbose))
    if getattr(args, "mark_damaged", False) and rep.damaged_frames:
        marked = mark_damaged(args.store, rep)
        print(f"marked {len(marked)} damaged frame(s) incomplete: {marked}; run the same "
              f"`python -m pipeline dataset` again to re-render them", file=sys.stderr)
    return rep.exit_code


def mark_damaged(path, rep: StoreReport) -> list[int]:
    """Mark ``rep``'s damaged frames incomplete (``StoreWriter.mark_failed``), so a resume re-renders
    and rewrites them. Returns the frames marked. Holds the store's writer lock (``stores.lock``)
    while it writes: StoreLockedError (nothing written) if a dataset run holds it."""
    from stores.errors import StoreLockedError
    from stores.lock import StoreLock
    from stores.writer import StoreWriter
    try:
        lock = StoreLock(path, command="validate --mark-damaged").acquire()
    except StoreLockedError as e:
        raise StoreLockedError(f"not marking the damaged frames {rep.damaged_frames} (nothing was written): {e}",
                               holder=e.holder) from e
    try:
        w = StoreWriter(path)
        why = {f.index: f.damage[0] for f in rep.frames if f.damage}
        out = list(rep.damaged_frames)
        w.commit({}, {i: f"damaged: {why.get(i, 'frames/status metadata chunk')}" for i in out})
    finally:
        lock.release()
    return out
