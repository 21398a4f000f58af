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
  radiance, Blosc LZ4 + byte shuffle); ``compact`` (the default for new stores) is built from zarr's
  own codecs only (:func:`image_chain`): channel-major inner chunks (``TransposeCodec``, samples
  innermost), mantissa rounding (``numcodecs.bitround``, ``KEEPBITS`` = 9 mantissa bits, relative
  error <= ``COMPACT_MAX_REL_ERROR`` = 2**-10) of input radiance, features, sample layers and guides,
  and Blosc LZ4HC-9 with bit shuffle; references stay lossless (zstd-5 + byte shuffle). Figures:
  SCHEMA.md ("Image encodings"). Our own code adds nothing to the chains: every codec is zarr's or
  numcodecs' (``decode`` of ``bitround`` is the identity, so any zarr v3 reader with numcodecs reads
  floats; xarray shows values, not codes).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

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

ENCODINGS = ("lz4", "compact")
LEGACY_ENCODING = "lz4"          # what a store whose layout records no ``encoding`` was written with
DEFAULT_ENCODING = "compact"     # what create_store uses when the layout leaves it open (None)
KEEPBITS = 9                     # mantissa bits kept by ``compact``'s bit rounding (float32 and float16)
COMPACT_MAX_REL_ERROR = 2.0 ** -(KEEPBITS + 1)     # 9.77e-4: round to nearest of a 9-bit mantissa
# the largest float16 with a 9-bit mantissa: zarr's BitRound rounds 65473..65504 up to 65536 = Inf
FLOAT16_MAX_COMPACT = float(np.float16(2.0 ** 15 * (2 - 2.0 ** -KEEPBITS)))
ZSTD_LEVEL = 5                   # Blosc zstd level of ``compact``'s lossless references
# Lossy arrays: LZ4HC-9 + bit shuffle. On real frames zstd-5 + bit shuffle is 5% smaller in total
# (features 0.080 vs 0.091 of float32) but its crops read 1.4x slower (SCHEMA.md "Image encodings").
LOSSY_BLOSC = ("lz4hc", 9, "bitshuffle")


@dataclass(frozen=True)
class Chain:
    """The inner-chunk codecs of one image array: ``sample_last`` (a ``TransposeCodec`` moving the
    sample axis innermost, so the 8 samples of a pixel lie together), ``keepbits`` (``BitRound``;
    None: lossless) and the Blosc compressor (``cname``, ``clevel``, ``shuffle``)."""

    cname: str
    clevel: int
    shuffle: str
    keepbits: int | None = None
    sample_last: bool = False

    def order(self, dims: tuple[str, ...]) -> tuple[int, ...] | None:
        """The ``TransposeCodec`` order over ``dims`` (frame first), None when nothing moves."""
        if not self.sample_last or "sample" not in dims:
            return None
        s = dims.index("sample")
        return tuple(i for i in range(len(dims)) if i != s) + (s,)


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


def image_chain(path: str, encoding: str, dtype: str) -> Chain:
    """The codecs of image array ``path`` under ``encoding`` for storage ``dtype`` (integer codes,
    i.e. log16 radiance, are never bit-rounded)."""
    if encoding == "lz4":
        return Chain(BLOSC["cname"], BLOSC["clevel"], BLOSC["shuffle"])
    if encoding != "compact":
        raise ValueError(f"unknown encoding {encoding!r}; known: {ENCODINGS}")
    c = _COMPACT.get(path, _LOSSY)                               # guides: lossy like the features
    if c.keepbits is not None and not np.dtype(dtype).kind == "f":
        c = replace(c, keepbits=None)
    return c


def bitround(x: np.ndarray, keepbits: int) -> np.ndarray:
    """``x`` (float32 or float16) with its mantissa rounded to nearest, ties to even, at ``keepbits``
    bits: exactly what zarr's ``numcodecs.bitround`` codec stores (the same implementation)."""
    from numcodecs import BitRound
    x = np.ascontiguousarray(x)
    return BitRound(keepbits).encode(x).view(x.dtype).reshape(x.shape)


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
    if chain.keepbits is not None:
        with warnings.catch_warnings():     # "numcodecs codecs are not in the Zarr v3 specification"
            warnings.simplefilter("ignore")
            out.append(BitRound(keepbits=chain.keepbits))
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
