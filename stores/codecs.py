"""Value encodings and the chunk compressor of the store (numpy and numcodecs only).

* ``compressor()``: Blosc LZ4 level 5 with byte shuffle, chosen by measurement (SCHEMA.md): about as
  small as zstd + bitshuffle on per-sample data and 3x faster to decode.
* ``checksum()`` / ``crc32c(data)``: the Zarr v3 ``crc32c`` codec appended to every chunk in schema v2,
  and the function the fast reader verifies it with.
* ``encode_log16`` / ``decode_log16``: an optional lossy radiance encoding (``radiance_encoding='log16'``).
  ``code = 0`` is exact zero; codes ``1 .. 65535`` cover ``[2**LOG16_MIN_EXP, 2**LOG16_MAX_EXP]``
  logarithmically, so the relative error is at most ``LOG16_MAX_REL_ERROR`` (3.4e-4) inside the range.
  Values below the range round to its lower end, values above clamp to the upper end (never Inf);
  negative values are stored as 0. Decoding is a 65536-entry float32 lookup table.
* ``ENCODINGS``: the codec chains of the image arrays, a store-wide choice recorded in the layout
  (``StoreLayout.encoding``). ``lz4`` is every store written before issue 13 (lossless float32
  radiance, Blosc LZ4 + byte shuffle); ``compact`` (the default of new stores until ``compact2``) is
  built from zarr's own codecs only (:func:`image_chain`): channel-major inner chunks (``TransposeCodec``, samples
  innermost), mantissa rounding (``numcodecs.bitround``, ``KEEPBITS`` = 9 mantissa bits, relative
  error <= ``COMPACT_MAX_REL_ERROR`` = 2**-10) of input radiance, features, sample layers and guides,
  and Blosc LZ4HC-9 with bit shuffle; references stay lossless (zstd-5 + byte shuffle). Figures:
  SCHEMA.md ("Image encodings"). Our own code adds nothing to the chains: every codec is zarr's or
  numcodecs' (``decode`` of ``bitround`` is the identity, so any zarr v3 reader with numcodecs reads
  floats; xarray shows values, not codes).
* ``compact3`` (the default of new stores): ``compact2``'s values, byte for byte, with chains of Zarr
  v3 specification codecs only (``sharding_indexed``, ``transpose``, ``bytes``, ``blosc``, ``crc32c``):
  the writer rounds every lossy array itself (``Chain.writer_rounds``, :func:`bitround`, the same
  numcodecs implementation), so no ``numcodecs.bitround`` is in any chain. Every Zarr v3 reader opens
  every array (tensorstore does not register numcodecs codecs), and zarr-python no longer warns that a
  codec is not in the specification.
* ``compact2`` (the default of new stores from issue 13 until ``compact3``): ``compact`` with each
  feature group rounded to its own mantissa bits (``FEATURE_KEEPBITS``, chosen by what a denoiser can
  use; input radiance and sample layers keep 9 bits). The writer rounds the features per group before
  the float16 cast (``Chain.channel_keepbits``, :func:`bitround_channels`); the chain's ``bitround``
  holds the largest of them, so it changes nothing more and any zarr reader decodes the values. The
  guides are rounded in the chain to their group's bits; references stay lossless (zstd-7 + byte
  shuffle, 1% smaller than ``compact``'s zstd-5). On real frames 0.178 of float32 against
  ``compact``'s 0.200 (SCHEMA.md "Measured: compact2").
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from stores.contract import FEATURE_GROUPS, FEATURE_NAMES

LOG16_MIN_EXP = -30.0        # 2**-30 ~ 9.3e-10
LOG16_MAX_EXP = 34.0         # 2**34 ~ 1.7e10 (>= 1e8 with room for fireflies)
_STEPS = 65534               # codes 1..65535
_STEP_LOG2 = (LOG16_MAX_EXP - LOG16_MIN_EXP) / _STEPS
LOG16_MAX_REL_ERROR = float(2.0 ** (_STEP_LOG2 / 2) - 1.0)
_LUT = np.concatenate([[0.0], 2.0 ** (LOG16_MIN_EXP + np.arange(_STEPS + 1) * _STEP_LOG2)]).astype(np.float32)


def encode_log16(x: np.ndarray) -> np.ndarray:
    """``x`` (float32, any shape, linear radiance) -> codes (uint16, same shape). NaN -> 0."""
    x = np.asarray(x, np.float32)
    pos = x > 0                                     # False for NaN, negatives and 0
    with np.errstate(divide="ignore", invalid="ignore"):
        lg = np.log2(np.where(pos, x, 1.0).astype(np.float64))
    code = np.rint((lg - LOG16_MIN_EXP) / _STEP_LOG2) + 1
    code = np.clip(code, 1, _STEPS + 1)
    return np.where(pos, code, 0).astype(np.uint16)


def decode_log16(code: np.ndarray) -> np.ndarray:
    """codes (uint16) -> linear radiance (float32, same shape)."""
    return _LUT[np.asarray(code, np.uint16)]


BLOSC = {"cname": "lz4", "clevel": 5, "shuffle": "shuffle"}     # the image arrays' compressor (SCHEMA.md)

ENCODINGS = ("lz4", "compact", "compact2", "compact3")
LEGACY_ENCODING = "lz4"          # what a store whose layout records no ``encoding`` was written with
DEFAULT_ENCODING = "compact3"    # what create_store uses when the layout leaves it open (None)
KEEPBITS = 9                     # mantissa bits kept by ``compact``'s bit rounding (float32 and float16)
COMPACT_MAX_REL_ERROR = 2.0 ** -(KEEPBITS + 1)     # 9.77e-4: round to nearest of a 9-bit mantissa
ZSTD_LEVEL = 5                   # Blosc zstd level of ``compact``'s lossless references
# Lossy arrays: LZ4HC-9 + bit shuffle. On real frames zstd-5 + bit shuffle is 5% smaller in total
# (features 0.080 vs 0.091 of float32) but its crops read 1.4x slower (SCHEMA.md "Image encodings").
LOSSY_BLOSC = ("lz4hc", 9, "bitshuffle")


# compact2: mantissa bits kept per feature group (stores.contract.FEATURE_GROUPS), what a denoiser can
# use (SCHEMA.md "compact2"); |x' - x| <= 2**-(k + 1) |x| for a group of k bits. Input radiance and the
# sample layers keep 9 bits (<= 2**-10 < 1e-3); the guides take their feature group's bits.
FEATURE_KEEPBITS = {
    "normal": 6,      # <= 2**-8 per unit-vector component (an 8-bit signed G-buffer normal): <= 0.4 degrees
    "depth": 8,       # <= 2**-9 relative (2 mm at 1 m)
    "albedo": 7,      # <= 2**-8 relative: below half an 8-bit sRGB step (>= 0.44%) at every level
    "specular": 7,    # a material colour, like albedo
    "roughness": 7,   # a material parameter in [0, 1], like albedo
    "motion": 8,      # <= 2**-9 relative: 1/32 px for motions up to 16 px
    "coc": 6,         # <= 2**-7 of the blur radius: 1/8 px for circles of confusion up to 16 px
    "lens": 4,        # <= 2**-6 of the lens radius a coordinate: ~CoC / 64 px on screen (1/4 px at 16 px)
    "time": 9,        # a few slice times a frame: coarser rounding saves nothing
}
GUIDE_GROUPS = {"guides/albedo": "albedo", "guides/normal": "normal", "guides/depth": "depth",
                "guides/motion": "motion"}
ZSTD_LEVEL_2 = 7                 # compact2's lossless references: 1% smaller than zstd-5, decode alike


def feature_keepbits(groups: dict[str, int] | None = None) -> tuple[int, ...]:
    """Mantissa bits of each of the 17 features (``FEATURE_NAMES`` order) under ``groups``
    (default :data:`FEATURE_KEEPBITS`)."""
    groups = FEATURE_KEEPBITS if groups is None else groups
    out = [0] * len(FEATURE_NAMES)
    for g, sl in FEATURE_GROUPS.items():
        for c in range(len(FEATURE_NAMES))[sl]:
            out[c] = int(groups[g])
    return tuple(out)


def float16_max(keepbits: int | None) -> float:
    """The largest |x| a float16 array takes when rounded to ``keepbits`` mantissa bits (None: no
    rounding, 65504): anything above would round up to 65536 = Inf."""
    if keepbits is None or keepbits >= 10:
        return 65504.0
    return float(2.0 ** 15 * (2 - 2.0 ** -keepbits))


@dataclass(frozen=True)
class Chain:
    """The inner-chunk codecs of one image array: ``sample_last`` (a ``TransposeCodec`` moving the
    sample axis innermost, so the 8 samples of a pixel lie together), ``keepbits`` (``BitRound``;
    None: lossless) and the Blosc compressor (``cname``, ``clevel``, ``shuffle``).
    ``channel_keepbits`` (not a codec): mantissa bits per entry of the ``channel_dim`` axis that the
    writer rounds to before the codecs (``ArraySpec.to_store``); ``keepbits`` is then their largest,
    so the chain's ``BitRound`` changes nothing more. ``writer_rounds`` (``compact3``): the writer does
    all the rounding (to ``channel_keepbits``, else ``keepbits``) and the chain holds no ``BitRound``;
    ``keepbits`` is still the precision the array keeps."""

    cname: str
    clevel: int
    shuffle: str
    keepbits: int | None = None
    sample_last: bool = False
    channel_keepbits: tuple[int, ...] | None = None
    channel_dim: str = "feature"
    writer_rounds: bool = False     # compact3: the writer rounds to ``keepbits``; no BitRound codec in the chain

    @property
    def codec_keepbits(self) -> int | None:
        """``keepbits`` of the chain's ``numcodecs.bitround`` codec (None: no such codec)."""
        return None if self.writer_rounds else self.keepbits

    def order(self, dims: tuple[str, ...]) -> tuple[int, ...] | None:
        """The ``TransposeCodec`` order over ``dims`` (frame first), None when nothing moves."""
        if not self.sample_last or "sample" not in dims:
            return None
        s = dims.index("sample")
        return tuple(i for i in range(len(dims)) if i != s) + (s,)

    def channel_bits(self, n: int) -> tuple[int | None, ...]:
        """Mantissa bits kept of each of ``n`` channels (None: lossless)."""
        return self.channel_keepbits if self.channel_keepbits is not None else (self.keepbits,) * n


_LOSSY = Chain(*LOSSY_BLOSC, KEEPBITS)
# The chains are part of the schema: open_group compares every array's zarr.json with them, so a
# change here would make the compact stores already written fail (ArrayMetadataError). Another chain
# is another ENCODINGS name, with image_chain giving both.
_COMPACT = {        # measured on real frames (SCHEMA.md "Image encodings")
    "inputs/radiance": replace(_LOSSY, sample_last=True),
    "inputs/features": replace(_LOSSY, sample_last=True),
    "layers/radiance": _LOSSY,                                   # level-last was 1% smaller: not worth a transpose
    "reference/radiance": Chain("zstd", ZSTD_LEVEL, "shuffle"),  # lossless: byte shuffle beats bit shuffle here
    "reference/stderr": Chain("zstd", ZSTD_LEVEL, "shuffle"),
}


def _compact2(path: str) -> Chain:
    """compact2's chain of ``path`` (from :data:`FEATURE_KEEPBITS`; like ``_COMPACT``, schema)."""
    if path == "inputs/features":
        bits = feature_keepbits()
        return replace(_LOSSY, keepbits=max(bits), sample_last=True, channel_keepbits=bits)
    if path in GUIDE_GROUPS:
        return replace(_LOSSY, keepbits=FEATURE_KEEPBITS[GUIDE_GROUPS[path]])
    if path.startswith("reference/"):
        return Chain("zstd", ZSTD_LEVEL_2, "shuffle")
    return _COMPACT.get(path, _LOSSY)                            # input radiance, layers: as compact


def image_chain(path: str, encoding: str, dtype: str) -> Chain:
    """The codecs of image array ``path`` under ``encoding`` for storage ``dtype`` (integer codes,
    i.e. log16 radiance, are never bit-rounded)."""
    if encoding == "lz4":
        return Chain(BLOSC["cname"], BLOSC["clevel"], BLOSC["shuffle"])
    if encoding == "compact":
        c = _COMPACT.get(path, _LOSSY)                           # guides: lossy like the features
    elif encoding == "compact2":
        c = _compact2(path)
    elif encoding == "compact3":                                 # compact2's values, spec codecs only
        c = replace(_compact2(path), writer_rounds=True)
    else:
        raise ValueError(f"unknown encoding {encoding!r}; known: {ENCODINGS}")
    if c.keepbits is not None and not np.dtype(dtype).kind == "f":
        c = replace(c, keepbits=None, channel_keepbits=None)
    return c


def bitround(x: np.ndarray, keepbits: int) -> np.ndarray:
    """``x`` (float32 or float16) with its mantissa rounded to nearest, ties to even, at ``keepbits``
    bits: exactly what zarr's ``numcodecs.bitround`` codec stores (the same implementation)."""
    from numcodecs import BitRound
    x = np.ascontiguousarray(x)
    return BitRound(keepbits).encode(x).view(x.dtype).reshape(x.shape)


def bitround_channels(x: np.ndarray, keepbits, axis: int) -> np.ndarray:
    """``x`` as float32 with entry ``c`` of ``axis`` rounded to ``keepbits[c]`` mantissa bits
    (:func:`bitround`; None keeps it exact)."""
    x = np.array(x, np.float32)                      # a copy: the caller's array stays as it is
    xm = np.moveaxis(x, axis, 0)
    if xm.shape[0] != len(keepbits):
        raise ValueError(f"{len(keepbits)} keepbits for an axis of {xm.shape[0]}")
    for k in sorted({b for b in keepbits if b is not None}):
        idx = [c for c, b in enumerate(keepbits) if b == k]
        xm[idx] = bitround(xm[idx], k)
    return x


def compressor(name: str = BLOSC["cname"], level: int = BLOSC["clevel"], shuffle: str = BLOSC["shuffle"]):
    """The zarr v3 Blosc codec used for every image array (``name``: lz4, lz4hc, zstd, zlib, blosclz)."""
    from zarr.codecs import BloscCodec
    return BloscCodec(cname=name, clevel=level, shuffle=shuffle)


def zarr_filters(chain: Chain, dims: tuple[str, ...]) -> list:
    """zarr array -> array codecs of ``chain`` (``TransposeCodec``, then ``BitRound``)."""
    import warnings

    from zarr.codecs import BitRound, TransposeCodec
    out = []
    order = chain.order(dims)
    if order is not None:
        out.append(TransposeCodec(order=order))
    if chain.codec_keepbits is not None:
        with warnings.catch_warnings():     # "numcodecs codecs are not in the Zarr v3 specification"
            warnings.simplefilter("ignore")
            out.append(BitRound(keepbits=chain.codec_keepbits))
    return out


def checksum():
    """Zarr v3's ``crc32c`` codec: the last codec of every chunk in schema v2 (4 bytes, little-endian
    CRC-32C of the encoded chunk, appended)."""
    from zarr.codecs import Crc32cCodec
    return Crc32cCodec()


def crc32c(data) -> int:
    """CRC-32C (Castagnoli) of ``data`` (bytes-like), as the ``crc32c`` codec and the shard index use it."""
    import google_crc32c
    return int(google_crc32c.value(np.frombuffer(data, np.uint8)))     # it takes no memoryview


def _quiet_numcodecs_warning() -> None:
    """zarr warns, on every array it opens, that ``numcodecs.bitround`` is not in the Zarr v3 spec.
    We know (SCHEMA.md names the codec; zarr-python and numcodecs read it); the warning would
    otherwise print once per array and process."""
    import warnings
    warnings.filterwarnings("ignore", message="Numcodecs codecs are not in the Zarr version 3 specification",
                            category=UserWarning)


_quiet_numcodecs_warning()
