"""Compiled (numba) decode loops of the SPZ reader: positions, rotations (v2 and smallest-three), SH rows.

Each is one pass over the bytes with its output written once, where the numpy forms in
``seggaussian.io.spz`` (``decode_fixed24_reference``, ``decode_rotations_v2_reference``,
``decode_rotations_v3_reference``, ``decode_sh_rows_reference``) make several passes and gathers over ``[N, ...]`` temporaries. They compute
the same float32 operations in the same order, so the results are bit-identical to those references
(tests/seggaussian/io/test_splat_formats.py checks every bit pattern class; benchmarks/bench_spz_ab.py
checks whole files). Each loop also applies the change of frame from the file's axes to the toolkit's RDF
(``seggaussian.io.spz.frame_signs``): one float32 multiplication by +-1 per value, exact. Serial, ``nogil``: a
gzip stream keeps inflating in its worker thread meanwhile.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["decode_fixed24", "decode_rotations_v2", "decode_rotations_v3", "decode_sh_rows"]

_JIT = dict(cache=True, nogil=True, error_model="numpy")


@numba.njit(**_JIT)
def decode_fixed24(raw: np.ndarray, scales: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``raw``: ``[M * 3]`` uint8, little-endian signed 24-bit integers; ``scales``: ``[3]`` float32, per axis
    +-``2^-fractional_bits`` (the sign the change of frame); ``out``: ``[M]`` float32 ``q * scales[i % 3]``
    (``M`` a multiple of 3, x y z interleaved; a power of two: exact)."""
    for i in range(out.shape[0]):
        q = np.int32(raw[3 * i]) | (np.int32(raw[3 * i + 1]) << 8) | (np.int32(raw[3 * i + 2]) << 16)
        if q >= 0x800000:
            q -= 0x1000000
        out[i] = np.float32(q) * scales[i % 3]


@numba.njit(**_JIT)
def decode_rotations_v2(raw: np.ndarray, signs: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``raw``: ``[N, 3]`` uint8 x, y, z as ``b / 127.5 - 1``; ``signs``: ``[4]`` float32 +-1 per output component
    (w, x, y, z); ``out``: ``[N, 4]`` float32 (w, x, y, z) times ``signs``, w the non-negative
    ``sqrt(1 - x^2 - y^2 - z^2)``."""
    scale, zero, one = np.float32(1.0 / 127.5), np.float32(0.0), np.float32(1.0)
    for i in range(raw.shape[0]):
        x = np.float32(raw[i, 0]) * scale - one
        y = np.float32(raw[i, 1]) * scale - one
        z = np.float32(raw[i, 2]) * scale - one
        out[i, 0] = np.sqrt(max(zero, one - (x * x + y * y + z * z))) * signs[0]
        out[i, 1], out[i, 2], out[i, 3] = x * signs[1], y * signs[2], z * signs[3]


@numba.njit(**_JIT)
def decode_rotations_v3(packed: np.ndarray, field_decode: np.ndarray, slots: np.ndarray, signs: np.ndarray,
                        out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``packed``: ``[N]`` uint32 smallest-three words; ``field_decode``: ``[1024]`` float32 value of a 10-bit
    field; ``slots``: ``[4, 4]`` per largest index, the source (field 0, 1, 2 or 3 = largest) of w, x, y, z;
    ``signs``: ``[4]`` float32 +-1 per output component; ``out``: ``[N, 4]`` float32 (w, x, y, z) times ``signs``."""
    values = np.empty(4, np.float32)
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(packed.shape[0]):
        word = packed[i]
        a = field_decode[word & 1023]
        b = field_decode[(word >> 10) & 1023]
        c = field_decode[(word >> 20) & 1023]
        values[0], values[1], values[2] = a, b, c
        values[3] = np.sqrt(max(zero, one - (a * a + b * b + c * c)))
        largest = word >> 30
        for j in range(4):
            out[i, j] = values[slots[largest, j]] * signs[j]


@numba.njit(**_JIT)
def decode_sh_rows(rest: np.ndarray, dc: np.ndarray, byte_value: np.ndarray, signs: np.ndarray,
                   out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``rest``: ``[M, 3 (K - 1)]`` uint8 SH bytes; ``dc``: ``[M, 3]`` float32; ``byte_value``: ``[256]`` float32;
    ``signs``: ``[3 (K - 1)]`` float32 +-1 per rest column; ``out``: ``[M, 3 K]`` float32 rows: the DC colour, then
    the decoded bytes times ``signs``."""
    for i in range(rest.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = dc[i, 0], dc[i, 1], dc[i, 2]
        for j in range(rest.shape[1]):
            out[i, 3 + j] = byte_value[rest[i, j]] * signs[j]
