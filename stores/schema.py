"""The store schema: the table of arrays (schema v3), the layout, and opening a store (``stores.create``
makes one, ``stores.chunk_files`` finds its chunk files, ``stores.upgrade`` turns an older store into one).

``open_group`` checks every array's ``zarr.json`` against the table (``array_problems``) and refuses a
store of an older schema version with a line naming ``python -m stores upgrade``. The per-frame metadata,
camera matrices and status are in chunks of :data:`META_CHUNK` frames committed by one process, the
SceneSpec JSON once a clip; every chunk carries a ``crc32c`` checksum (the inner chunks of shards too) and
every chunk of a complete frame is written (so a missing file is damage, not zeros); coordinates for
xarray (``G/frame`` 0..F-1 in every group, ``rgb``/``xyz``/``uv`` labels, ``layers/level`` with
``layers/spp`` as its non-index coordinate) and consolidated metadata. ``stores/SCHEMA.md`` has the table.

One Zarr v3 group per dataset (see ``stores/SCHEMA.md`` for the table with dtypes, chunks and the
measurements behind them). Images are stored sample-major, the ``(S, C, h, w)`` layout training
consumes (no transpose on read): ``inputs/radiance (float32, F·sample·rgb·y·x)``, sharded one shard per frame and per array with
``tile x tile`` inner chunks, so a training crop of one frame with all samples reads a few inner
chunks of one file, and each writer task owns whole shards (no locks). Every array carries ``dimension_names`` so ``xarray.open_zarr(store, group=...)``
reads each group with named dims.

The renderer's per-frame dict (``stores.contract.FRAME_ARRAYS``, channel-last) maps to the arrays
below through :class:`ArraySpec` (``to_store`` / ``from_store`` transpose between the two layouts).
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

from core.checks import need, need_int
from stores import codecs
from stores.contract import FEATURE_NAMES, FRAME_META, LAYER_SPP, NUM_FEATURES
from stores.errors import (ArrayMetadataError, ForeignStoreError, IncompleteStoreError,
                           StoreLayoutError, StoreNotFoundError, raise_if_unreachable)

SCHEMA_VERSION = 3                 # what create_store writes and every reader and writer takes
COORD_CHUNK = 1024                 # chunk length of the ``frame`` coordinates (they grow with the store)
META_CHUNK = 1024                  # frames a chunk of the per-frame metadata and status arrays hold
STORE_KIND = "denoise-datagen.sample-store"
RADIANCE_ENCODINGS = ("float32", "log16")
FEATURE_DTYPES = ("float16", "float32")
FLOAT16_MAX = 65504.0


SHAPE_FIELDS = ("num_frames", "height", "width", "spp", "layer_spp")   # StoreLayout fields set by the frames


@dataclass(frozen=True)
class StoreLayout:
    """Shape and encoding of a store: ``num_frames`` frames of ``height x width`` pixels, ``spp`` input
    samples and one sample layer per entry of ``layer_spp`` (each the mean of that many samples).

    ``tile`` is the inner chunk edge in pixels (clamped to the frame). ``radiance_encoding`` is
    ``float32`` (default) or ``log16`` (uint16 log code, rel. error <= 3.4e-4).
    ``feature_dtype`` is ``float16`` (default; values must stay within +-65504) or ``float32``.
    ``encoding`` is the image arrays' codec chains (``stores.codecs.ENCODINGS``): ``compact3``
    (``compact2``'s values with the writer doing all rounding: Zarr v3 specification codecs only),
    ``compact2``
    (``compact`` with each feature group and guide rounded to its own mantissa bits,
    ``codecs.FEATURE_KEEPBITS``), ``compact`` (bit-rounded inputs, layers and guides, rel. error
    <= 2**-10; lossless references; zstd) or ``lz4`` (everything lossless, LZ4). None leaves it open:
    ``create_store`` makes a new store ``compact3`` and an existing store keeps its own, so a config
    that does not name it resumes stores of any. A stored layout without the key is a store written
    before the field existed (``lz4``); ``to_dict`` omits None, so configs that leave it open keep
    their old form.
    """

    num_frames: int
    height: int
    width: int
    spp: int = 8
    layer_spp: tuple[int, ...] = LAYER_SPP
    tile: int = 32
    radiance_encoding: str = "float32"
    feature_dtype: str = "float16"
    encoding: str | None = None

    def __post_init__(self):
        for name in ("num_frames", "height", "width", "spp", "tile"):
            need_int(f'"{name}"', getattr(self, name), 0 if name == "num_frames" else 1, None, StoreLayoutError,
                     numpy=True)
        object.__setattr__(self, "layer_spp", tuple(int(s) for s in self.layer_spp))
        if any(s < 1 for s in self.layer_spp):
            raise StoreLayoutError(f'"layer_spp" must hold positive sample counts, got {self.layer_spp!r}')
        need(self.radiance_encoding in RADIANCE_ENCODINGS, '"radiance_encoding"', f"one of {RADIANCE_ENCODINGS}",
             self.radiance_encoding, StoreLayoutError)
        need(self.feature_dtype in FEATURE_DTYPES, '"feature_dtype"', f"one of {FEATURE_DTYPES}", self.feature_dtype,
             StoreLayoutError)
        need(self.encoding is None or self.encoding in codecs.ENCODINGS, '"encoding"',
             f"one of {codecs.ENCODINGS} (or left out)", self.encoding, StoreLayoutError)

    @property
    def codec_set(self) -> str:
        """The encoding in force: ``encoding``, or the default for new stores when it is left open."""
        return self.encoding or codecs.DEFAULT_ENCODING

    def resolved(self) -> "StoreLayout":
        """This layout with ``encoding`` decided (what ``create_store`` records)."""
        return self if self.encoding else replace(self, encoding=self.codec_set)

    @property
    def feature_limits(self) -> tuple[float, ...]:
        """The largest |x| of each feature a float16 store takes: 65504, less where the encoding rounds
        the mantissa (9 bits: 65472; bit rounding would turn anything above into Inf)."""
        spec = ARRAY_BY_PATH["inputs/features"]
        return tuple(codecs.float16_max(k) for k in spec.chain(self).channel_bits(NUM_FEATURES))

    @property
    def num_layers(self) -> int:
        return len(self.layer_spp)

    @classmethod
    def encoding_fields(cls) -> tuple[str, ...]:
        """The fields a dataset config chooses (``dataset.store``); the others (:data:`SHAPE_FIELDS`)
        follow from its frames, resolution and render settings."""
        return tuple(f.name for f in fields(cls) if f.name not in SHAPE_FIELDS)

    @property
    def tile_y(self) -> int:
        return min(self.tile, self.height)

    @property
    def tile_x(self) -> int:
        return min(self.tile, self.width)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["layer_spp"] = list(self.layer_spp)
        if d["encoding"] is None:          # left open: no key (the form of every layout before the field)
            del d["encoding"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "StoreLayout":
        """A layout from ``to_dict`` form. For a store's recorded layout (``open_group``) a missing
        ``encoding`` means the store predates the field: :data:`stores.codecs.LEGACY_ENCODING`."""
        d = dict(d)
        d["layer_spp"] = tuple(d.get("layer_spp", LAYER_SPP))
        return cls(**d)

    @classmethod
    def of_store(cls, d: dict) -> "StoreLayout":
        """The layout recorded in a store's root attributes (``encoding`` always decided)."""
        return cls.from_dict({"encoding": codecs.LEGACY_ENCODING, **d})

    def with_frames(self, num_frames: int) -> "StoreLayout":
        return replace(self, num_frames=num_frames)

    def frame_shape_compatible(self, other: "StoreLayout") -> bool:
        """Same frames and encodings, ``num_frames`` aside; an ``encoding`` left open (None) on either
        side matches any."""
        a, b = self.to_dict(), other.to_dict()
        a.pop("num_frames"), b.pop("num_frames")
        if "encoding" not in a or "encoding" not in b:
            a.pop("encoding", None), b.pop("encoding", None)
        return a == b


@dataclass(frozen=True)
class ArraySpec:
    """One array of the schema: its ``path`` in the group, ``dims`` (frame first), storage ``dtype``,
    the contract key it comes from (``source``, or a ``FRAME_META`` key for ``frames/*``) and how
    the contract's channel-last array is transposed into storage (``perm``; ``squeeze`` drops a last
    axis of size 1)."""

    path: str
    dims: tuple[str, ...]
    dtype: str
    source: str
    doc: str
    perm: tuple[int, ...] | None = None
    squeeze: bool = False
    image: bool = True
    fill: Any = 0
    coord: str = ""             # "" per-frame data; else a coordinate written at creation (see coord_values)
    labels: tuple[str, ...] = ()    # the values of a ``labels`` coordinate
    xr_coords: str = ""         # names of non-index coordinates (xarray's ``coordinates`` attribute)
    frame_chunk: int = 1        # frames a chunk holds (metadata: META_CHUNK, written by one process)
    clip_first: bool = False    # ``frames/scene_json``: written only at each clip's first frame

    @property
    def per_frame(self) -> bool:
        """Written by each frame's task (one chunk or shard per frame), as opposed to a coordinate."""
        return not self.coord

    def to_store(self, a: np.ndarray, layout: StoreLayout) -> np.ndarray:
        """Contract layout (channel-last) -> storage layout and dtype, for one frame."""
        a = np.asarray(a)
        if self.squeeze:
            a = a[..., 0]
        if self.perm is not None:
            a = a.transpose(self.perm)
        if self.path == "inputs/radiance" and layout.radiance_encoding == "log16":
            return codecs.encode_log16(a)
        dtype = self.storage_dtype(layout)
        if self.image:
            ch = self.chain(layout)
            if ch.channel_keepbits is not None:
                # compact2/3's features: each channel to its own bits, in float32, before the cast (the
                # codec's BitRound, if any, keeps the largest of them, so it changes nothing more)
                a = codecs.bitround_channels(a, ch.channel_keepbits, self.dims.index(ch.channel_dim) - 1)
            elif ch.keepbits is not None and dtype == "float16" and a.dtype != np.float16:
                # round once, in float32, to the bits kept: the float16 cast is then exact (for
                # |x| >= 2**-14) and the codec's BitRound a no-op; f32 -> f16 -> 9 bits would round twice
                a = codecs.bitround(np.asarray(a, np.float32), ch.keepbits)
            elif ch.keepbits is not None and ch.writer_rounds:
                # compact3: no BitRound codec in the chain; the same rounding, done here
                a = codecs.bitround(np.asarray(a, dtype), ch.keepbits)
        return np.ascontiguousarray(a, dtype=dtype)

    def chain(self, layout: StoreLayout) -> "codecs.Chain":
        """This image array's inner-chunk codecs under the layout's encoding."""
        return codecs.image_chain(self.path, layout.codec_set, self.storage_dtype(layout))

    def from_store(self, a: np.ndarray, layout: StoreLayout) -> np.ndarray:
        """Storage layout (any leading frame axis kept; log16 radiance already decoded, as
        ``Store.read_array`` returns it) -> contract layout (channel-last), float32 for images."""
        if self.perm is not None:
            inv = np.argsort(self.perm)
            lead = a.ndim - len(self.perm)
            a = a.transpose(tuple(range(lead)) + tuple(lead + int(i) for i in inv))
        if self.squeeze:
            a = a[..., None]
        if self.image:
            a = a.astype(np.float32, copy=False)
        return a

    def storage_dtype(self, layout: StoreLayout) -> str:
        if self.path == "inputs/radiance" and layout.radiance_encoding == "log16":
            return "uint16"
        if self.path == "inputs/features":
            return layout.feature_dtype
        return self.dtype

    def shape(self, layout: StoreLayout) -> tuple[int, ...]:
        sizes = {"frame": layout.num_frames, "rgb": 3, "xyz": 3, "uv": 2, "y": layout.height,
                 "x": layout.width, "sample": layout.spp, "feature": NUM_FEATURES,
                 "level": layout.num_layers, "row": 4, "col": 4}
        return tuple(sizes[d] for d in self.dims)

    def chunks(self, layout: StoreLayout) -> tuple[int, ...]:
        """Inner chunk shape: one frame x one spatial tile x everything else (coordinates: one chunk,
        ``COORD_CHUNK`` frames for a ``frame`` coordinate)."""
        if self.coord == "frame":
            return (COORD_CHUNK,)
        if self.coord:
            return self.shape(layout)
        tiles = {"y": layout.tile_y, "x": layout.tile_x}
        return tuple(self.frame_chunk if d == "frame" else tiles.get(d, s)
                     for d, s in zip(self.dims, self.shape(layout)))

    def shards(self, layout: StoreLayout) -> tuple[int, ...] | None:
        """Shard shape: one whole frame (spatial extent rounded up to whole tiles); None for scalars."""
        if not self.image:
            return None
        out = []
        for d, s, c in zip(self.dims, self.shape(layout), self.chunks(layout)):
            out.append(1 if d == "frame" else -(-s // c) * c)
        return tuple(out)


_IMAGE_SPECS = (
    ArraySpec("inputs/radiance", ("frame", "sample", "rgb", "y", "x"), "float32", "radiance",
              "per-sample linear HDR radiance", perm=(2, 3, 0, 1)),
    ArraySpec("inputs/features", ("frame", "sample", "feature", "y", "x"), "float16", "features",
              "per-sample features, names in inputs/feature", perm=(2, 3, 0, 1)),
    ArraySpec("layers/radiance", ("frame", "level", "rgb", "y", "x"), "float32", "layers",
              "sample layer n: mean of layer_spp[n] independent samples", perm=(0, 3, 1, 2)),
    ArraySpec("reference/radiance", ("frame", "rgb", "y", "x"), "float32", "reference",
              "reference radiance (per-pixel mean)", perm=(2, 0, 1)),
    ArraySpec("reference/stderr", ("frame", "rgb", "y", "x"), "float32", "reference_stderr",
              "standard error of the reference mean", perm=(2, 0, 1)),
    ArraySpec("guides/albedo", ("frame", "rgb", "y", "x"), "float32", "guides_albedo",
              "per-pixel albedo", perm=(2, 0, 1)),
    ArraySpec("guides/normal", ("frame", "xyz", "y", "x"), "float32", "guides_normal",
              "per-pixel world-space normal", perm=(2, 0, 1)),
    ArraySpec("guides/depth", ("frame", "y", "x"), "float32", "guides_depth",
              "per-pixel depth", squeeze=True),
    ArraySpec("guides/motion", ("frame", "uv", "y", "x"), "float32", "guides_motion",
              "per-pixel screen-space motion in pixels, p_prev - p_cur", perm=(2, 0, 1)),
)
_MATRIX_SPECS = (
    ArraySpec("frames/camera_to_world", ("frame", "row", "col"), "float64", "camera_to_world",
              "camera-to-world matrix", image=False),
    ArraySpec("frames/world_to_clip", ("frame", "row", "col"), "float64", "world_to_clip",
              "projection * view (NDC in [-1, 1])", image=False),
)
_META_DTYPES = {str: "str", int: "int64", bool: "bool", float: "float64"}
_META_SPECS = tuple(
    ArraySpec(f"frames/{k}", ("frame",), _META_DTYPES[t], k, f"frame metadata {k!r}", image=False,
              fill="" if t is str else (False if t is bool else 0))
    for k, t in FRAME_META.items()) + (
    ArraySpec("frames/clip_id", ("frame",), "int64", "clip_id",
              "clip (scene) id: frames of one clip share it; defaults to scene_seed", image=False),)
_STATUS_SPECS = (
    ArraySpec("status/error", ("frame",), "str", "error",
              "error text of the last failed attempt ('' if none)", image=False, fill=""),
    ArraySpec("status/complete", ("frame",), "bool", "complete",
              "True once every array of the frame is written; written last", image=False, fill=False),
)
GROUPS = ("inputs", "layers", "reference", "guides", "frames", "status")
# The FRAME_META keys every store has had since the start. A ``frames/*`` array of a key added since
# (``stores.contract.FRAME_META`` grows, e.g. ``case``) is missing from stores made before it: not
# damage (:func:`absent_arrays`); readers give its fill value, ``open_or_create`` adds it.
BASE_META_KEYS = ("scene_json", "scene_seed", "frame", "num_frames", "has_motion", "has_defocus",
                  "nonfinite_inputs", "nonfinite_layers", "nonfinite_reference", "reference_spp",
                  "reference_rel_stderr", "render_seconds")


def _coords() -> tuple[ArraySpec, ...]:
    """The coordinates xarray reads: ``G/frame`` 0..F-1 in every group, channel labels, levels."""
    out = [ArraySpec(f"{g}/frame", ("frame",), "int64", "", "frame index 0..F-1 (the frame coordinate)",
                     image=False, coord="frame") for g in GROUPS]
    for g, dim, labels in (("inputs", "rgb", "rgb"), ("layers", "rgb", "rgb"), ("reference", "rgb", "rgb"),
                           ("guides", "rgb", "rgb"), ("guides", "xyz", "xyz"), ("guides", "uv", "uv")):
        out.append(ArraySpec(f"{g}/{dim}", (dim,), "str", "", f"channel labels of {dim}", image=False,
                             fill="", coord="labels", labels=tuple(labels)))
    out += [ArraySpec("inputs/feature", ("feature",), "str", "", "feature names (stores.contract.FEATURE_NAMES)",
                      image=False, fill="", coord="labels", labels=FEATURE_NAMES),
            ArraySpec("layers/level", ("level",), "int32", "", "level index 0..L-1", image=False, coord="level"),
            ArraySpec("layers/spp", ("level",), "int32", "", "samples averaged in each level (coordinate of level)",
                      image=False, coord="spp")]
    return tuple(out)


def _current(spec: ArraySpec) -> ArraySpec:
    """A spec as this schema stores it: the per-frame metadata, camera matrices and status in chunks of
    :data:`META_CHUNK` frames, written by one process (the dataset run's client,
    ``stores.writer.StoreWriter.commit``); the SceneSpec JSON once a clip, at its first frame
    (``clip_first``), written by the scene's own task; the index in the clip as ``frames/frame_in_clip``
    (``frames/frame`` would collide with the frame dimension in xarray)."""
    if spec.path == "frames/frame":
        spec = replace(spec, path="frames/frame_in_clip", doc="index of the frame in its clip")
    if spec.path == "layers/radiance":
        return replace(spec, xr_coords="spp")
    if spec.path == "frames/scene_json":
        return replace(spec, clip_first=True, doc="SceneSpec JSON of the clip, at its first frame only "
                                                  "(frame_in_clip 0; '' elsewhere)")
    if spec.per_frame and not spec.image:
        return replace(spec, frame_chunk=META_CHUNK)
    return spec


ARRAYS: tuple[ArraySpec, ...] = tuple(_current(s) for s in _IMAGE_SPECS + _MATRIX_SPECS + _META_SPECS
                                      + _STATUS_SPECS) + _coords()
ARRAY_BY_PATH = {s.path: s for s in ARRAYS}
ARRAY_BY_SOURCE = {s.source: s for s in _IMAGE_SPECS + _MATRIX_SPECS}


def meta_path(key: str) -> str:
    """Path of the ``frames/*`` array holding ``FRAME_META`` key (or ``clip_id``): ``frame`` ->
    ``frames/frame_in_clip``."""
    for spec in ARRAYS:
        if spec.path.startswith("frames/") and spec.source == key and spec.per_frame:
            return spec.path
    raise KeyError(key)


def later_meta_paths() -> tuple[str, ...]:
    """Paths of the ``frames/*`` arrays of FRAME_META keys added after :data:`BASE_META_KEYS`."""
    return tuple(meta_path(k) for k in FRAME_META if k not in BASE_META_KEYS)


def absent_arrays(root) -> frozenset[str]:
    """The arrays of :func:`later_meta_paths` that the store at ``root`` lacks (it was made before
    their key existed). Every other array must be there (:func:`array_problems`)."""
    out = []
    for path in later_meta_paths():
        try:
            root[path]
        except KeyError:
            out.append(path)
    return frozenset(out)


def coord_values(spec: ArraySpec, layout: StoreLayout) -> np.ndarray:
    """The values of a coordinate array."""
    if spec.coord == "frame":
        return np.arange(layout.num_frames, dtype=np.int64)
    if spec.coord == "level":
        return np.arange(layout.num_layers, dtype=np.int32)
    if spec.coord == "spp":
        return np.asarray(layout.layer_spp, np.int32)
    if spec.coord == "labels":
        return np.array(spec.labels)
    raise ValueError(f"{spec.path} is not a coordinate")


def create_kwargs(spec: ArraySpec, layout: StoreLayout) -> dict:
    """``zarr.Group.create_array`` keyword arguments of ``spec``: image arrays sharded with Blosc inner
    chunks, metadata chunks (many frames each) Blosc zstd, other scalars uncompressed; the ``crc32c``
    codec last on every (inner) chunk."""
    dtype = spec.storage_dtype(layout)
    crc = [codecs.checksum()]
    attrs = {"doc": spec.doc, "source": spec.source}
    if spec.xr_coords:
        attrs["coordinates"] = spec.xr_coords
    kw = dict(shape=spec.shape(layout), dtype=str if dtype == "str" else dtype, chunks=spec.chunks(layout),
              dimension_names=spec.dims, fill_value=spec.fill, attributes=attrs)
    if spec.image:
        ch = spec.chain(layout)
        kw.update(shards=spec.shards(layout), filters=codecs.zarr_filters(ch, spec.dims) or None,
                  compressors=[codecs.compressor(ch.cname, ch.clevel, ch.shuffle)] + crc)
    elif spec.frame_chunk > 1:         # metadata: a chunk of 1024 frames, mostly fill in a small store
        kw.update(compressors=[codecs.compressor(*META_BLOSC)] + crc)
    else:
        kw.update(compressors=crc)
    return kw


META_BLOSC = ("zstd", 3, "shuffle")    # metadata chunks: a 4-frame store's 1024-frame camera matrices 1.2 KB, not 128


def expected_codecs(spec: ArraySpec, layout: StoreLayout) -> tuple:
    """The codec chain the schema gives ``spec``, in :func:`codec_signature`'s form."""
    crc = (("crc32c",),)
    ser = ("vlen-utf8",) if spec.storage_dtype(layout) == "str" else ("bytes", "little")
    if spec.image:
        ch = spec.chain(layout)
        order = ch.order(spec.dims)
        pre = ((("transpose", ("order", json.dumps(list(order)))),) if order is not None else ()) + \
              ((("numcodecs.bitround", ("keepbits", json.dumps(ch.keepbits))),) if ch.codec_keepbits is not None else ())
        inner = pre + (("bytes", "little"), ("blosc", ch.cname, ch.clevel, ch.shuffle)) + crc
        return (("sharding_indexed", spec.chunks(layout), inner, (("bytes", "little"), ("crc32c",)), "end"),)
    if spec.frame_chunk > 1:
        return (ser, ("blosc",) + META_BLOSC) + crc
    return (ser,) + crc


def codec_signature(chain) -> tuple:
    """A ``zarr.json`` codec list reduced to what decoding depends on (names, byte order, Blosc
    compressor/level/shuffle, sharding's inner chunks and index), for comparison with the schema."""
    out = []
    for c in chain or ():
        name, conf = c.get("name"), c.get("configuration") or {}
        if name == "bytes":
            out.append(("bytes", conf.get("endian", "little")))
        elif name == "blosc":
            out.append(("blosc", conf.get("cname"), conf.get("clevel"), conf.get("shuffle")))
        elif name == "sharding_indexed":
            out.append((name, tuple(conf.get("chunk_shape", ())), codec_signature(conf.get("codecs")),
                        codec_signature(conf.get("index_codecs")), conf.get("index_location", "end")))
        else:
            out.append((name,) + tuple(sorted((k, json.dumps(v)) for k, v in conf.items())))
    return tuple(out)


_DATA_TYPES = {"str": "string"}


def array_problems(root, layout: StoreLayout, *, frames_exact: bool = True) -> list[str]:
    """Every way the arrays' metadata (``zarr.json``) differs from the schema's table: a
    missing array, data type, shape, chunk/shard shape, chunk key encoding, codecs, fill value,
    dimension names. ``frames_exact=False`` accepts a frame axis longer than ``layout.num_frames``
    (a writer re-opening a store whose growth was cut short; ``grow`` finishes it)."""
    out = []
    later = set(later_meta_paths())
    for spec in ARRAYS:
        try:
            arr = root[spec.path]
            meta = arr.metadata.to_dict()
        except KeyError:
            if spec.path not in later:      # a key newer than the store: read as its fill value
                out.append(f"{spec.path}: missing")
            continue
        except Exception as e:    # noqa: BLE001 - zarr raises many types for an unparsable zarr.json
            raise_if_unreachable(e, doing=f"reading {spec.path}/zarr.json")
            out.append(f"{spec.path}: unreadable zarr.json ({type(e).__name__}: {e})")
            continue
        if meta.get("node_type") != "array":
            out.append(f"{spec.path}: not an array")
            continue
        name = spec.path
        dt = spec.storage_dtype(layout)
        want_dt = _DATA_TYPES.get(dt, dt)
        if meta.get("data_type") != want_dt:
            out.append(f"{name}: data_type {meta.get('data_type')!r}, the schema says {want_dt!r}")
        shape, want = tuple(meta.get("shape", ())), spec.shape(layout)
        frame_ok = (len(shape) == len(want) and spec.dims[0] == "frame" and not frames_exact
                    and shape[0] >= want[0] and shape[1:] == want[1:])
        if shape != want and not frame_ok:
            out.append(f"{name}: shape {shape}, the layout says {want}")
        grid = meta.get("chunk_grid", {})
        got_chunks = tuple((grid.get("configuration") or {}).get("chunk_shape", ()))
        want_chunks = spec.shards(layout) if spec.image else spec.chunks(layout)
        if grid.get("name") != "regular" or got_chunks != tuple(want_chunks):
            out.append(f"{name}: chunk grid {grid.get('name')} {got_chunks}, "
                       f"the schema says regular {tuple(want_chunks)}")
        key = meta.get("chunk_key_encoding", {})
        if key.get("name") != "default" or (key.get("configuration") or {}).get("separator", "/") != "/":
            out.append(f"{name}: chunk key encoding {key}, the schema says default with '/'")
        got_c, want_c = codec_signature(meta.get("codecs")), expected_codecs(spec, layout)
        if got_c != want_c:
            out.append(f"{name}: codecs {got_c}, the schema says {want_c}")
        fill = meta.get("fill_value")
        if fill != spec.fill or type(fill) is bool and type(spec.fill) is not bool:
            out.append(f"{name}: fill_value {fill!r}, the schema says {spec.fill!r}")
        if tuple(meta.get("dimension_names") or ()) != spec.dims:
            out.append(f"{name}: dimension names {meta.get('dimension_names')}, the schema says {list(spec.dims)}")
    return out


def consolidate(path_or_url) -> None:
    """Write consolidated metadata (zarr-python's extension of the root ``zarr.json``), so
    ``xarray.open_zarr(path, group=G)`` opens without a warning. Call after every metadata change
    (creation, growth, root attributes): a write of the root attributes through a handle opened
    without it drops it again. The package's own readers never use it (``use_consolidated=False``)."""
    import warnings

    import zarr
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Consolidated metadata", category=UserWarning)
        # a dataset run's lock file (stores.lock) sits in the root folder while the run lives
        warnings.filterwarnings("ignore", message=f"Object at {LOCK_NAME} is not recognized", category=UserWarning)
        zarr.consolidate_metadata(_zarr_store(path_or_url))


def _zarr_store(path_or_url):
    return os.fspath(path_or_url) if isinstance(path_or_url, os.PathLike) else path_or_url


LOCK_NAME = "dataset.lock"   # the writer's lock file in a store's folder (stores.lock); not store data
CREATION_ATTR = "creating"   # root attribute present only while create_store is running


def _is_local(p) -> bool:
    return not (isinstance(p, str) and "://" in p)


def store_exists(path_or_url) -> bool:
    """Whether a Zarr v3 group (a root ``zarr.json``) is at ``path_or_url``. Only "not found" means no:
    any other failure (permissions, network, a broken URL) is raised."""
    p = _zarr_store(path_or_url)
    if _is_local(p):
        return os.path.isfile(os.path.join(p, "zarr.json"))
    import zarr
    try:
        zarr.open_group(p, mode="r")
        return True
    except FileNotFoundError:   # zarr's NodeNotFoundError / GroupNotFoundError are FileNotFoundErrors
        return False


def open_group(path_or_url, mode: str = "r", *, check: bool = True):
    """Open an existing store's root group after checking it is ours and of this schema version (an older
    one is refused by ``stores.upgrade.require_current`` with a line naming ``python -m stores upgrade``),
    and (``check``) that every array's metadata matches the table (:func:`array_problems`). Returns
    ``(group, layout)``. Raises StoreNotFoundError, ForeignStoreError, IncompleteStoreError (creation was
    cut short), SchemaVersionError, ArrayMetadataError (an edited or damaged ``zarr.json``). Consolidated
    metadata is never used here (it may be stale)."""
    import zarr
    if not store_exists(path_or_url):
        if isinstance(path_or_url, (str, os.PathLike)) and os.path.exists(os.fspath(path_or_url)):
            raise ForeignStoreError(f"{path_or_url!s} exists but is not a Zarr v3 group (no zarr.json)")
        raise StoreNotFoundError(f"no store at {path_or_url!s}")
    try:
        root = zarr.open_group(_zarr_store(path_or_url), mode=mode, use_consolidated=False)
    except Exception as e:  # noqa: BLE001
        raise_if_unreachable(e, path_or_url, "opening it")
        raise ForeignStoreError(f"{path_or_url!s} is not a readable Zarr group: {e}") from e
    attrs = dict(root.attrs)
    if attrs.get("kind") != STORE_KIND:
        raise ForeignStoreError(f"{path_or_url!s} is a Zarr group but not a {STORE_KIND} store "
                                f"(root attribute 'kind' is {attrs.get('kind')!r})")
    if CREATION_ATTR in attrs:
        c = attrs[CREATION_ATTR] if isinstance(attrs[CREATION_ATTR], dict) else {}
        raise IncompleteStoreError(
            f"{path_or_url!s} was never finished: its creation by pid {c.get('pid')} on {c.get('host')} "
            f"(started {c.get('started')}) was cut short; run `python -m pipeline dataset` again to make it",
            creator=c)
    from stores.upgrade import require_current
    require_current(path_or_url, attrs, SCHEMA_VERSION)
    layout = StoreLayout.of_store(attrs["layout"])
    if check:
        bad = array_problems(root, layout, frames_exact=(mode == "r"))
        if bad:
            raise ArrayMetadataError(f"{path_or_url!s}: array metadata disagrees with schema v{SCHEMA_VERSION} "
                                     f"({len(bad)} problem(s)): " + "; ".join(bad),
                                     array=bad[0].split(":")[0])
    return root, layout


def grow(root, layout: StoreLayout, num_frames: int) -> StoreLayout:
    """Grow every per-frame array to ``num_frames`` (never shrinks). Metadata only; call it from one
    process (the graph's driver) before tasks write the new frames."""
    if num_frames <= layout.num_frames:
        return layout
    new = layout.with_frames(num_frames)
    absent = absent_arrays(root)
    for spec in ARRAYS:
        if spec.dims[0] != "frame" or spec.path in absent:
            continue
        arr = root[spec.path]
        arr.resize((num_frames,) + tuple(arr.shape[1:]))
        if spec.coord == "frame":
            arr.with_config({"write_empty_chunks": True})[:] = coord_values(spec, new)
    root.attrs["layout"] = new.to_dict()
    consolidate(root.store)
    return new


def add_absent_arrays(root, layout: StoreLayout) -> list[str]:
    """Create the :func:`absent_arrays` of an existing store (opened ``r+``; one process, before
    tasks write), every existing frame's chunk written with the fill value, so complete frames keep
    one file per array (a missing file is damage). Returns the paths created."""
    made = []
    for path in sorted(absent_arrays(root)):
        arr = root.create_array(path, **create_kwargs(ARRAY_BY_PATH[path], layout))
        if arr.shape[0]:
            arr.with_config({"write_empty_chunks": True})[:] = ARRAY_BY_PATH[path].fill
        made.append(path)
    if made:
        consolidate(root.store)
    return made


__all__ = ["SCHEMA_VERSION", "STORE_KIND", "meta_path",
           "array_problems", "create_kwargs", "consolidate", "StoreLayout", "ArraySpec", "ARRAYS",
           "ARRAY_BY_PATH", "ARRAY_BY_SOURCE", "GROUPS", "open_group", "grow", "FLOAT16_MAX"]
