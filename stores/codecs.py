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
"""
from __future__ import annotations

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


def compressor(name: str = BLOSC["cname"], level: int = BLOSC["clevel"], shuffle: str = BLOSC["shuffle"]):
    """The zarr v3 Blosc codec used for every image array (``name``: lz4, lz4hc, zstd, zlib, blosclz)."""
    from zarr.codecs import BloscCodec
    return BloscCodec(cname=name, clevel=level, shuffle=shuffle)


def checksum():
    """Zarr v3's ``crc32c`` codec: the last codec of every chunk in schema v2 (4 bytes, little-endian
    CRC-32C of the encoded chunk, appended)."""
    from zarr.codecs import Crc32cCodec
    return Crc32cCodec()


def crc32c(data) -> int:
    """CRC-32C (Castagnoli) of ``data`` (bytes-like), as the ``crc32c`` codec and the shard index use it."""
    import google_crc32c
    return int(google_crc32c.value(np.frombuffer(data, np.uint8)))     # it takes no memoryview
