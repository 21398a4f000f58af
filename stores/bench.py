"""Store benchmark: crop read speed against a raw ``np.load`` ceiling, stored/raw bytes, codec table.

``run() -> dict`` prints and returns:

* ``crops_per_s``, ``mb_per_s``: random 128x128 crops with all 8 samples of radiance + 17 features
  (what ``training.datasets.SampleFrames`` reads), from a store on local disk, through the reader's fast path; MB are
  float32 bytes delivered (128*128*8*20*4 = 10.5 MB a crop). ``zarr_*``: the same through zarr-python.
* ``ceiling_*``: ``np.load`` of the same crop as one uncompressed float32 ``.npy`` file;
  ``fraction_of_ceiling`` = mb_per_s / ceiling_mb_per_s (target >= 0.5).
* ``stored_over_raw``: bytes of the image arrays' files / their float32 bytes.
* ``codecs``: the candidate encodings on the same frames (ratio, decode ms a frame).
* ``crc_ms_per_frame``: the crc32c arithmetic alone over one frame's image shards (every chunk carries
  one; stores/SCHEMA.md has what the checksums cost when schema v2 brought them).

Data: ``store=PATH`` benchmarks an existing store; by default a temporary store of synthetic frames
(``tests/test_stores_synthetic.py``: HDR with fireflies, constant regions) is written first, in the
default (``compact3``, ``compact2``'s values in spec-only chains) encoding.

``reencode(paths)`` (``--reencode STORE ...``): a few complete frames of each real store written again
into a ``compact3``, a ``compact`` and an ``lz4`` store: stored bytes / float32 bytes per array group
and in total, the errors of the lossy encodings (input radiance: max and 99.9th percentile of
``|x' - x| / |x|`` over non-zero samples; zeros must stay zero; the max per feature group, layers
and guides), write (encode) ms per frame, and the crop read of each store against the ``np.load``
ceiling (:func:`run` on it).
"""
from __future__ import annotations

import importlib.util
import os
import shutil
import tempfile
import time

import numpy as np

from stores import chunk_files, schema
from stores.reader import open_store
from stores.schema import ARRAYS, StoreLayout
from stores.writer import open_or_create


def _synthetic():
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests",
                        "test_stores_synthetic.py")
    if not os.path.exists(path):
        raise FileNotFoundError(f"the benchmark's synthetic frames come from {path} (run from a checkout) "
                                f"or pass store=PATH")
    spec = importlib.util.spec_from_file_location("_stores_synthetic", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.synthetic_frame


def _dir_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(path) for f in fs
               if f != "zarr.json")


def _codec_cases() -> list[tuple]:
    """The candidate encodings of :func:`compare_codecs`: ``(name, Blosc codec (None: raw bytes),
    radiance encoder, feature dtype or rounding ("br16", "grp16"), layout ("sm", "cm"))``."""
    from numcodecs import Blosc

    from stores.codecs import KEEPBITS, bitround, encode_log16
    lz4 = Blosc("lz4", 5, Blosc.SHUFFLE)
    zstd = Blosc("zstd", 3, Blosc.BITSHUFFLE)
    lz4b = Blosc("lz4", 5, Blosc.BITSHUFFLE)
    ident = lambda r: r  # noqa: E731
    cases = [
        ("raw float32", None, ident, np.float32, "sm"),
        ("float16 (radiance overflows > 65504)", None, lambda r: r.astype(np.float16), np.float16, "sm"),
        ("float32, zstd-3 + bitshuffle", zstd, ident, np.float32, "sm"),
        ("float32, lz4-5 + shuffle", lz4, ident, np.float32, "sm"),
        ("float32 + f16 features, zstd-3 + bitshuffle", zstd, ident, np.float16, "sm"),
        ("float32 + f16 features, lz4-5 + bitshuffle", lz4b, ident, np.float16, "sm"),
        ("float32 + f16 features, lz4-5 + shuffle (the lz4 encoding)", lz4, ident, np.float16, "sm"),
        ("  the same, channel-major (C,H,W,S)", lz4, ident, np.float16, "cm"),
        ("log16 radiance + f16 features, lz4-5 + shuffle", lz4, encode_log16, np.float16, "sm"),
    ]
    br = lambda r: bitround(r, KEEPBITS)  # noqa: E731
    lz4hc = Blosc("lz4hc", 9, Blosc.BITSHUFFLE)
    cases += [
        ("compact3 = compact2: 9-bit radiance, features per group, lz4hc-9 + bitshuffle, (C,H,W,S) (chosen)",
         lz4hc, br, "grp16", "cm"),
        ("  the same, zstd-5 + bitshuffle", Blosc("zstd", 5, Blosc.BITSHUFFLE), br, "grp16", "cm"),
        ("compact: 9-bit radiance + features, lz4hc-9 + bitshuffle, (C,H,W,S)", lz4hc, br, "br16", "cm"),
        ("  the same, sample-major (S,C,H,W)", lz4hc, br, "br16", "sm"),
        ("  the same (C,H,W,S), zstd-5 + bitshuffle", Blosc("zstd", 5, Blosc.BITSHUFFLE), br, "br16", "cm"),
    ]
    return cases


def _encode_inputs(r: np.ndarray, f: np.ndarray, enc_r, fdt, lay: str) -> tuple[np.ndarray, np.ndarray]:
    """One frame's radiance ``r`` and features ``f`` (layout ``lay``) as a case of :func:`_codec_cases`
    hands them to its codec, each contiguous."""
    from stores.codecs import KEEPBITS, bitround, bitround_channels, feature_keepbits
    with np.errstate(over="ignore"):
        if fdt == "br16":                 # compact's features: rounded once in float32, then float16
            ef = np.ascontiguousarray(bitround(f, KEEPBITS).astype(np.float16))
            er = np.ascontiguousarray(enc_r(r))
        elif fdt == "grp16":              # compact2's: each feature group to its own bits
            ef = bitround_channels(f, feature_keepbits(), {"sm": 1, "cm": 0}[lay]).astype(np.float16)
            ef = np.ascontiguousarray(ef)
            er = np.ascontiguousarray(enc_r(r))
        else:
            er, ef = np.ascontiguousarray(enc_r(r)), np.ascontiguousarray(f.astype(fdt))
    return er, ef


def _codec_row(case: tuple, rads: list, feats: list, raw: int) -> dict:
    """One row of :func:`compare_codecs`: ``case`` (of :func:`_codec_cases`) over the frames' radiance
    ``rads`` and features ``feats`` in its layout; ``raw``: their float32 bytes."""
    from stores.codecs import decode_log16
    name, codec, enc_r, fdt, lay = case
    nbytes, dec_s = 0, 0.0
    overflow = 0
    for r, f in zip(rads, feats):
        er, ef = _encode_inputs(r, f, enc_r, fdt, lay)
        overflow += int(np.isinf(er.astype(np.float32)).sum()) if er.dtype == np.float16 else 0
        if codec is None:
            nbytes += er.nbytes + ef.nbytes
            continue
        br, bf = codec.encode(er), codec.encode(ef)
        nbytes += len(br) + len(bf)
        t = time.perf_counter()
        dr = np.frombuffer(codec.decode(br), er.dtype)
        if er.dtype == np.uint16:
            dr = decode_log16(dr)
        np.frombuffer(codec.decode(bf), ef.dtype)
        dec_s += time.perf_counter() - t
    return {"encoding": name, "ratio": nbytes / raw, "decode_ms_per_frame": 1e3 * dec_s / len(rads),
            "inf_after_encoding": overflow}


def compare_codecs(frames: list[dict]) -> list[dict]:
    """Per-sample inputs (radiance + features) of ``frames`` under candidate encodings, whole frames
    sample-major ``(S, C, H, W)`` like the store (one row channel-major ``(C, H, W, S)``): ratio to
    float32 bytes and decode time per frame."""
    layouts = {"sm": (2, 3, 0, 1), "cm": (3, 0, 1, 2)}
    rad_l = {k: [np.ascontiguousarray(f["radiance"].transpose(p)) for f in frames] for k, p in layouts.items()}
    feat_l = {k: [np.ascontiguousarray(f["features"].transpose(p)) for f in frames] for k, p in layouts.items()}
    raw = sum(r.nbytes + f.nbytes for r, f in zip(rad_l["sm"], feat_l["sm"]))
    return [_codec_row(case, rad_l[case[4]], feat_l[case[4]], raw) for case in _codec_cases()]


def _crc_seconds(path: str, images: list[str]) -> tuple[float, int]:
    """The checksum arithmetic alone: seconds of CRC-32C over every byte of frame 0's image shards in
    the store at ``path`` (mean of 5), and those bytes."""
    from stores.codecs import crc32c
    blobs = [open(os.path.join(path, *a.split("/"), *chunk_files.chunk_key(schema.ARRAY_BY_PATH[a], 0).split("/")),
                  "rb").read() for a in images]
    t = time.perf_counter()
    for _ in range(5):
        for b in blobs:
            crc32c(b)
    return (time.perf_counter() - t) / 5, sum(len(b) for b in blobs)


def _write_synthetic(store: str, *, frames: int, size: int, spp: int, encoding: str | None) -> tuple[list, float]:
    """Write ``frames`` synthetic frames to a new store at ``store``: (the frames, write seconds a frame)."""
    synth = _synthetic()
    w = open_or_create(store, StoreLayout(num_frames=frames, height=size, width=size, spp=spp,
                                          encoding=encoding), {"bench": True})
    frame_list = []
    t_write = 0.0
    for i in range(frames):
        fr = synth(1000 + i, size, size, spp, sun=(i == 0))
        frame_list.append(fr)
        t = time.perf_counter()
        w.write_frame(i, fr)
        t_write += time.perf_counter() - t
    return frame_list, t_write / frames


def _crop_read_ways(s, store, tmp: str, crop: int, spp: int) -> dict:
    """The crop reads :func:`run` times, by name, each ``fn(i, y, x)``: the fast path (``s``), zarr-python,
    2 read threads, float32 tensors (``SampleFrames``' read), the ``np.load`` ceiling and, where tiles
    are square, tile-aligned crops."""
    lay = s.layout
    zs = open_store(store, fast=False)
    import torch

    def tensors(i, y, x):        # what training.datasets.SampleFrames makes of a crop: float32 tensors
        for name in ("inputs/radiance", "inputs/features"):
            a = s.read_array(name, i, (y, x, crop, crop), samples=spp)
            torch.from_numpy(np.ascontiguousarray(a)).to(torch.float32)
    tile = lay.tile_y
    npy = os.path.join(tmp, "crop.npy")
    np.save(npy, np.zeros((spp, 20, crop, crop), np.float32))

    def read(st, i, y, x):
        st.read_array("inputs/radiance", i, (y, x, crop, crop), samples=spp)
        st.read_array("inputs/features", i, (y, x, crop, crop), samples=spp)

    st2 = open_store(store, threads=2)
    ways = {"fast": lambda i, y, x: read(s, i, y, x), "zarr": lambda i, y, x: read(zs, i, y, x),
            "threads2": lambda i, y, x: read(st2, i, y, x),
            "tensors": tensors,
            "ceiling": lambda i, y, x: np.load(npy)}
    if lay.tile_x == tile:
        ways["aligned"] = lambda i, y, x: read(s, i, (y // tile) * tile, (x // tile) * tile)
    return ways


def _interleaved_median_s(ways: dict, picks: list) -> dict:
    """Median seconds of each of ``ways`` over ``picks``, after one warm-up call each; all ways back to
    back a pick."""
    times = {k: [] for k in ways}
    for k, fn in ways.items():                 # warm the page cache and the readers
        fn(*picks[0])
    for i, y, x in picks:                      # interleaved, so machine load hits all alike
        for k, fn in ways.items():
            t = time.perf_counter()
            fn(i, y, x)
            times[k].append(time.perf_counter() - t)
    return {k: float(np.median(v)) for k, v in times.items()}


def _crop_figures(med: dict, *, encoding: str, crop: int, spp: int, crops: int, mb: float) -> dict:
    """:func:`run`'s crop-read figures from the median seconds ``med`` of :func:`_crop_read_ways`."""
    out = {
        "encoding": encoding, "crop": crop, "spp": spp, "crops": crops, "mb_per_crop": mb,
        "crops_per_s": 1 / med["fast"], "mb_per_s": mb / med["fast"],
        "zarr_crops_per_s": 1 / med["zarr"], "zarr_mb_per_s": mb / med["zarr"],
        "tensor_crops_per_s": 1 / med["tensors"], "tensor_mb_per_s": mb / med["tensors"],
        "ceiling_crops_per_s": 1 / med["ceiling"], "ceiling_mb_per_s": mb / med["ceiling"],
        "fraction_of_ceiling": med["ceiling"] / med["fast"],
        "tensor_fraction_of_ceiling": med["ceiling"] / med["tensors"],
    }
    out.update({"threads2_crops_per_s": 1 / med["threads2"], "threads2_mb_per_s": mb / med["threads2"],
                "threads2_fraction_of_ceiling": med["ceiling"] / med["threads2"]})
    if "aligned" in med:
        out.update({"aligned_crops_per_s": 1 / med["aligned"], "aligned_mb_per_s": mb / med["aligned"],
                    "aligned_fraction_of_ceiling": med["ceiling"] / med["aligned"]})
    return out


def _stored_over_raw(store, lay: StoreLayout, frames: int) -> float:
    """Bytes of the image arrays' files / their float32 bytes over ``frames`` frames."""
    stored = raw = 0
    for spec in ARRAYS:
        if spec.image:
            stored += _dir_bytes(os.path.join(os.fspath(store), *spec.path.split("/")))
            raw += int(np.prod(spec.shape(lay)[1:])) * 4 * frames
    return stored / max(raw, 1)


def run(store=None, *, crops: int = 40, crop: int = 128, spp: int = 8, frames: int = 4, size: int = 256,
        compare: bool = True, checksums: bool = True, verbose: bool = True, encoding: str | None = None) -> dict:
    """Run the benchmark (module docstring) and return its figures (``encoding``: of the synthetic
    store; None is the default of new stores)."""
    tmp = tempfile.mkdtemp(prefix="stores-bench-")
    out: dict = {}
    try:
        frame_list = []
        if store is None:
            store = os.path.join(tmp, "bench.zarr")
            frame_list, out["write_s_per_frame"] = _write_synthetic(store, frames=frames, size=size, spp=spp,
                                                                    encoding=encoding)
        s = open_store(store)
        lay = s.layout
        crop = min(crop, lay.height, lay.width)
        spp = min(spp, lay.spp)
        done = s.complete_frames()
        rng = np.random.default_rng(0)
        picks = [(int(rng.choice(done)), int(rng.integers(0, lay.height - crop + 1)),
                  int(rng.integers(0, lay.width - crop + 1))) for _ in range(crops)]
        mb = crop * crop * spp * 20 * 4 / 1e6
        med = _interleaved_median_s(_crop_read_ways(s, store, tmp, crop, spp), picks)
        out.update(_crop_figures(med, encoding=lay.encoding, crop=crop, spp=spp, crops=crops, mb=mb))
        out["stored_over_raw"] = _stored_over_raw(store, lay, len(done))
        if compare and frame_list:
            out["codecs"] = compare_codecs(frame_list)
        if checksums and frame_list:
            crc_s, nbytes = _crc_seconds(store, [sp.path for sp in ARRAYS if sp.image])
            out["checksums"] = {"crc_ms_per_frame": 1e3 * crc_s, "crc_gb_per_s": nbytes / crc_s / 1e9,
                                "frame_shard_bytes": nbytes}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if verbose:
        print(format_report(out))
    return out


def format_report(r: dict) -> str:
    lines = [f"stores bench: {r['crops']} random {r['crop']}x{r['crop']} crops x {r['spp']} samples "
             f"(radiance + 17 features, {r['mb_per_crop']:.1f} MB float32 each), {r['encoding']} store",
             f"  store (fast path) {r['crops_per_s']:8.1f} crops/s {r['mb_per_s']:8.0f} MB/s",
             f"  store, 2 read threads {r['threads2_crops_per_s']:4.1f} crops/s {r['threads2_mb_per_s']:8.0f} MB/s",
             f"  store (zarr-python) {r['zarr_crops_per_s']:6.1f} crops/s {r['zarr_mb_per_s']:8.0f} MB/s",
             f"  as float32 tensors (S,C,h,w) {r['tensor_crops_per_s']:6.1f} crops/s {r['tensor_mb_per_s']:6.0f} MB/s"
             f"  (SampleFrames' read)",
             f"  tile-aligned crops {r.get('aligned_crops_per_s', float('nan')):7.1f} crops/s "
             f"{r.get('aligned_mb_per_s', float('nan')):8.0f} MB/s (crop_align = tile)",
             f"  np.load ceiling   {r['ceiling_crops_per_s']:8.1f} crops/s {r['ceiling_mb_per_s']:8.0f} MB/s",
             f"  fraction of ceiling {r['fraction_of_ceiling']:.2f} (as tensors {r['tensor_fraction_of_ceiling']:.2f};"
             f" target >= 0.5)",
             f"  stored / raw float32 bytes {r['stored_over_raw']:.3f}"]
    if "write_s_per_frame" in r:
        lines.append(f"  write {r['write_s_per_frame'] * 1e3:.0f} ms per frame")
    ck = r.get("checksums")
    if ck:
        lines.append(f"  CRC-32C alone over one frame's {ck['frame_shard_bytes'] / 1e6:.1f} MB of image shards: "
                     f"{ck['crc_ms_per_frame']:.2f} ms ({ck['crc_gb_per_s']:.1f} GB/s)")
    for row in r.get("codecs", []):
        lines.append(f"    {row['encoding']:80s} ratio {row['ratio']:.3f}  decode {row['decode_ms_per_frame']:6.1f} ms/frame"
                     + (f"  Inf: {row['inf_after_encoding']}" if row["inf_after_encoding"] else ""))
    return "\n".join(lines)


GROUP_OF = {"inputs/radiance": "inputs/radiance", "inputs/features": "inputs/features",
            "layers/radiance": "layers", "reference/radiance": "reference", "reference/stderr": "reference"}
REENCODINGS = ("compact3", "compact", "lz4")     # what --reencode writes: the default of new stores first


def _rel_error(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``|y - x| / |x|`` (float64) over the non-zero entries of ``x``."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    nz = x != 0
    return np.abs(y[nz] - x[nz]) / np.abs(x[nz])


def _write_reencoded(dst: str, lay: StoreLayout, data: list[dict], source) -> list[float]:
    """Write the frames ``data`` into a new store at ``dst`` of layout ``lay``: seconds of each write."""
    w = open_or_create(dst, lay, {"reencoded_from": os.fspath(source)})
    t_write = []
    for j, fr in enumerate(data):
        t = time.perf_counter()
        w.write_frame(j, fr)
        t_write.append(time.perf_counter() - t)
    return t_write


def _group_bytes(dst: str, lay: StoreLayout, frames: int) -> tuple[dict, dict]:
    """Stored bytes and float32 bytes of ``frames`` frames, by array group (:data:`GROUP_OF`)."""
    sizes, raw = {}, {}
    for spec in ARRAYS:
        if spec.image:
            g = GROUP_OF.get(spec.path, "guides")
            sizes[g] = sizes.get(g, 0) + _dir_bytes(os.path.join(dst, *spec.path.split("/")))
            raw[g] = raw.get(g, 0) + int(np.prod(spec.shape(lay)[1:])) * 4 * frames
    return sizes, raw


def _readback_errors(dst: str, data: list[dict], e: dict, row: dict) -> None:
    """Read the frames back from ``dst``: their relative errors against ``data`` appended to ``e`` (lists
    by key), zeros of the input radiance that changed and whether the references are bit-exact into ``row``."""
    from stores.contract import FEATURE_GROUPS
    back = open_store(dst)
    for j, fr in enumerate(data):
        got = back.read_frame(j)
        e.setdefault("radiance", []).append(_rel_error(fr["radiance"], got["radiance"]))
        for g, sl in FEATURE_GROUPS.items():
            e.setdefault(f"features/{g}", []).append(_rel_error(fr["features"][..., sl],
                                                                got["features"][..., sl]))
        for k in ("layers", "guides_albedo", "guides_normal", "guides_depth", "guides_motion"):
            e.setdefault(k, []).append(_rel_error(fr[k], got[k]))
        row["zeros_changed"] += int((got["radiance"][fr["radiance"] == 0] != 0).sum())
        row["reference_bit_exact"] &= bool(np.array_equal(got["reference"], fr["reference"])
                                           and np.array_equal(got["reference_stderr"],
                                                              fr["reference_stderr"]))


def _reencode_store(path, tmp: str, *, frames: int, crops: int, encodings: tuple[str, ...],
                    tot: dict, raw_tot: dict, errs: dict) -> dict:
    """:func:`reencode` of the store at ``path``: its row; its bytes added to ``tot`` (stored, by
    encoding and group) and ``raw_tot`` (float32, by group), its errors to ``errs`` (by encoding)."""
    src = open_store(path)
    done = src.complete_frames()
    pick = sorted({done[int(k)] for k in np.linspace(0, len(done) - 1, min(frames, len(done)))})
    data = [src.read_frame(i) for i in pick]
    lay0 = src.layout
    row: dict = {"frames": pick, "source_encoding": lay0.encoding, "zeros_changed": 0,
                 "reference_bit_exact": True}
    for enc in encodings:
        lay = StoreLayout(**{**lay0.to_dict(), "num_frames": len(pick), "encoding": enc})
        dst = os.path.join(tmp, f"{os.path.basename(os.fspath(path).rstrip('/'))}-{enc}.zarr")
        t_write = _write_reencoded(dst, lay, data, path)
        sizes, raw = _group_bytes(dst, lay, len(pick))
        for g in sizes:
            tot[enc][g] = tot[enc].get(g, 0) + sizes[g]
            if enc == encodings[0]:
                raw_tot[g] = raw_tot.get(g, 0) + raw[g]
        row[enc] = {"ratio": {g: sizes[g] / raw[g] for g in sizes},
                    "total": sum(sizes.values()) / sum(raw.values()),
                    "write_ms_per_frame": 1e3 * float(np.median(t_write)),
                    "crop_read": run(dst, crops=crops, compare=False, checksums=False, verbose=False)}
        if enc != "lz4":
            _readback_errors(dst, data, errs[enc], row)
    return row


def _error_summary(errs: dict) -> dict:
    """By encoding with errors: the input radiance's max, 99.9th percentile, mean and samples, and the
    max of every other key's errors (0 where it has none)."""
    out = {}
    for enc, e in errs.items():
        if not e:
            continue
        rad = np.concatenate(e.pop("radiance"))
        out[enc] = {"radiance": {"max": float(rad.max()), "p99.9": float(np.percentile(rad, 99.9)),
                                 "mean": float(rad.mean()), "samples": int(rad.size)}}
        out[enc].update({k: float(max((a.max() for a in v if a.size), default=0.0)) for k, v in e.items()})
    return out


def reencode(paths, *, frames: int = 4, crops: int = 40, verbose: bool = True,
             encodings: tuple[str, ...] = REENCODINGS) -> dict:
    """Write ``frames`` complete frames (evenly spaced) of each store in ``paths`` into a new store of
    each of ``encodings`` and report, per store and over all: stored/float32 bytes per group
    (``inputs/radiance``, ``inputs/features``, ``layers``, ``reference`` (+ stderr), ``guides``) and in
    total, write ms per frame, the crop read of each new store, and for the lossy encodings the
    errors (``errors[enc]``: max and 99.9th percentile of ``|x' - x| / |x|`` of the input radiance over
    non-zero samples, max per feature group and per guide; zeros must stay zero, references
    bit-exact). ``radiance_rel_error`` is that of ``encodings[0]``. Measure from a lossless (``lz4``)
    store: re-encoding a lossy one measures nothing but the difference."""
    tmp = tempfile.mkdtemp(prefix="stores-reencode-")
    out: dict = {"stores": {}, "encodings": list(encodings)}
    tot = {e: {} for e in encodings}
    raw_tot: dict = {}
    errs: dict = {e: {} for e in encodings}
    try:
        for path in paths:
            out["stores"][os.fspath(path)] = _reencode_store(path, tmp, frames=frames, crops=crops,
                                                             encodings=encodings, tot=tot, raw_tot=raw_tot,
                                                             errs=errs)
        out["errors"] = _error_summary(errs)
        first = next((enc for enc in encodings if enc in out["errors"]), None)
        if first:
            out["radiance_rel_error"] = out["errors"][first]["radiance"]
        out["all"] = {enc: {"ratio": {g: tot[enc][g] / raw_tot[g] for g in raw_tot},
                            "total": sum(tot[enc].values()) / sum(raw_tot.values())} for enc in tot}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if verbose:
        print(format_reencode(out))
    return out


def format_reencode(r: dict) -> str:
    encs = r.get("encodings") or list(r["all"])
    groups = list(r["all"][encs[0]]["ratio"])
    lines = ["stores bench --reencode: stored / float32 bytes (features counted as float32)",
             f"  {'store':24s} {'encoding':9s} " + " ".join(f"{g:>15s}" for g in groups)
             + f" {'total':>7s}  write ms/frame"]
    for path, row in list(r["stores"].items()) + [("all", r["all"])]:
        for enc in encs:
            c = row[enc]
            wr = f"  {c['write_ms_per_frame']:6.1f}" if "write_ms_per_frame" in c else ""
            lines.append(f"  {os.path.basename(path):24s} {enc:9s} " + " ".join(f"{c['ratio'][g]:15.3f}" for g in groups)
                         + f" {c['total']:7.3f}{wr}")
    for enc, e in r.get("errors", {}).items():
        rad = e["radiance"]
        lines.append(f"  {enc} radiance |x'-x|/|x| over {rad['samples']} non-zero samples: max {rad['max']:.3e}, "
                     f"99.9% {rad['p99.9']:.3e}, mean {rad['mean']:.3e}")
        lines.append(f"  {enc} max |x'-x|/|x|: " + ", ".join(f"{k} {v:.2e}" for k, v in e.items() if k != "radiance"))
    lines.append(f"  zeros changed: {sum(row.get('zeros_changed', 0) for row in r['stores'].values())}; "
                 f"references bit-exact: {all(row.get('reference_bit_exact') for row in r['stores'].values())}")
    for path, row in r["stores"].items():
        for enc in encs:
            c = row[enc]["crop_read"]
            lines.append(f"  crop read {os.path.basename(path)} ({enc}, {c['crop']}x{c['crop']} x {c['spp']} spp): "
                         f"{c['crops_per_s']:.1f} crops/s vs np.load {c['ceiling_crops_per_s']:.1f}: "
                         f"{c['fraction_of_ceiling']:.2f} of the ceiling (as tensors "
                         f"{c['tensor_fraction_of_ceiling']:.2f})")
    return "\n".join(lines)
