"""Splat formats without the reference converter: detection by content, round trips within each format's
quantisation step, layout details, errors, the palette and the CLI (see test_splat_reference.py for the
comparison with @playcanvas/splat-transform and test_splat_fuzz.py for malformed files)."""

from __future__ import annotations

import gzip
import json
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from seggaussian.core.constants import IGNORE_LABEL, SH_C0
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import (FORMATS, detect_format, format_for_output, read_gaussians, read_gaussians_raw,
                                    scene_stem, write_gaussians)
from seggaussian.io.splat_common import SplatFormatError


def _gaussians(n: int = 300, degree: int = 2, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    return Gaussians.from_arrays(rng.uniform(-5, 5, (n, 3)), rng.normal(size=(n, 4)) * 3, rng.uniform(-8, 2, (n, 3)),
                                 rng.normal(0, 3, n), np.concatenate([rng.uniform(-1.7, 1.7, (n, 1, 3)),
                                                                     rng.uniform(-0.9, 0.9, (n, k - 1, 3))], 1))


def _quat_error(a, b):
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.minimum(np.abs(a - b).max(1), np.abs(a + b).max(1))


@pytest.mark.parametrize("fmt, kwargs", [("ply", {}), ("compressed_ply", {}), ("splat", {}),
                                         ("spz", {"spz_version": 2}), ("spz", {"spz_version": 3}),
                                         ("spz", {"spz_version": 4}), ("ksplat", {"ksplat_level": 0}),
                                         ("ksplat", {"ksplat_level": 1}), ("ksplat", {"ksplat_level": 2})])
def test_round_trip_within_quantisation_and_detected_by_content(fmt, kwargs, tmp_path):
    from seggaussian.io.ksplat import bucket_layout

    g = _gaussians(degree=0 if fmt == "splat" else 2)
    path = tmp_path / "scene.bin"                      # no telling extension
    assert write_gaussians(path, g, fmt, **kwargs) == fmt
    assert detect_format(path) == fmt
    back, report, detected = read_gaussians(path)
    assert detected == fmt and report.ok and len(back) == len(g) and back.sh_degree == g.sh_degree
    if fmt == "compressed_ply":                        # stored in Morton order, as the reference writes it
        from seggaussian.io.compressed_ply import morton_order

        g = g.subset(morton_order(g.means))
    if (level := kwargs.get("ksplat_level")) is not None:
        fmt = f"ksplat{level}"                         # tolerances per compression level below
        if level:                                      # levels 1-2 store the splats bucket by bucket
            g = g.subset(bucket_layout(g.means).order)
    # steps: see each module's docstring
    half16 = 2.0 ** -11                                # float16 relative rounding (ksplat levels 1-2)
    pos = {"ply": 0, "splat": 0, "spz": 0.5 / 4096, "compressed_ply": np.ptp(g.means, 0) / 1023,
           "ksplat0": 0, "ksplat1": 2.5 / 32767 / 2, "ksplat2": 2.5 / 32767 / 2}[fmt]
    assert (np.abs(back.means - g.means) <= pos + 1e-5).all()
    scale = {"ply": 0, "splat": 1e-6, "spz": 0.5 / 16, "compressed_ply": np.ptp(g.log_scales, 0) / 1023,
             "ksplat0": 1e-6, "ksplat1": half16, "ksplat2": half16}[fmt]
    assert (np.abs(back.log_scales - g.log_scales) <= scale + 1e-5).all()
    assert (np.abs(back.opacities() - g.opacities()) <= (0 if fmt == "ply" else 0.5 / 255) + 1e-5).all()
    dc = {"ply": 0, "splat": 0.5 / 255 / SH_C0, "spz": 0.5 / 255 / 0.15,
          "compressed_ply": np.ptp(g.dc_colors(), 0) / 255 / SH_C0}.get(fmt, 0.5 / 255 / SH_C0)
    assert (np.abs(back.sh[:, 0] - g.sh[:, 0]) <= dc + 1e-5).all()
    rest = {"ply": 0, "spz": 0.5 / 128, "compressed_ply": 8 / 256, "ksplat0": 0, "ksplat1": half16,
            "ksplat2": 0.5 * 2 * np.abs(g.sh[:, 1:]).max(initial=0) / 255}.get(fmt)
    if rest is not None:
        assert (np.abs(back.sh[:, 1:] - g.sh[:, 1:]) <= rest + 1e-5).all()
    if fmt == "spz" and kwargs["spz_version"] == 2:
        unit = g.normalized_quats() * np.where(g.normalized_quats()[:, :1] < 0, -1, 1)
        assert (np.abs(back.quats[:, 1:] - unit[:, 1:]) <= 1 / 127.5).all()   # w is derived (see spz.py)
    else:
        assert (_quat_error(back.quats, g.quats) <= {"ply": 1e-6, "splat": 1 / 127.5, "spz": 1 / 511,
                                                      "compressed_ply": np.sqrt(2) / 1023, "ksplat0": 1e-6,
                                                      "ksplat1": half16, "ksplat2": half16}[fmt] + 1e-5).all()


def test_spz_gzip_wrapped_and_raw_payload_decode_identically(tmp_path):
    from seggaussian.io.spz import decode_spz, encode_spz

    g = _gaussians(degree=3)
    for version in (2, 3):
        wrapped = encode_spz(g, version)
        assert wrapped[:2] == b"\x1f\x8b"
        raw = gzip.decompress(wrapped)
        assert raw[:4] == b"NGSP" and struct.unpack_from("<I", raw, 4)[0] == version
        a, b = decode_spz(wrapped), decode_spz(raw)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    v4 = encode_spz(g, 4)
    assert v4[:4] == b"NGSP" and struct.unpack_from("<IB", v4, 4)[0] == 4


def test_spz_v4_layout_and_sh_degree_4_refused(tmp_path):
    from seggaussian.io.spz import V4_HEADER, encode_spz

    g = _gaussians(degree=0, n=10)
    data = bytearray(encode_spz(g, 4))
    magic, version, n, degree, frac, flags, streams, toc, _ = V4_HEADER.unpack_from(data)
    assert (version, n, degree, frac, streams, toc) == (4, 10, 0, 12, 5, 32)   # no SH stream for degree 0
    data[12] = 4                                                               # claim SH degree 4
    path = tmp_path / "deg4.spz"
    path.write_bytes(bytes(data))
    with pytest.raises(SplatFormatError, match=r"deg4.spz: Niantic SPZ: SH degree 4 is not supported"):
        read_gaussians(path)


def test_compressed_ply_layout(tmp_path):
    from seggaussian.io.ply.header import read_ply_header

    g = _gaussians(n=600, degree=1)
    path = tmp_path / "a.compressed.ply"
    write_gaussians(path, g)
    header = read_ply_header(path)
    assert [(e.name, e.count) for e in header.elements] == [("chunk", 3), ("vertex", 600), ("sh", 600)]
    assert [p.name for p in header.element("sh").properties] == [f"f_rest_{i}" for i in range(9)]
    # a chunk count that does not match ceil(N / 256) names both numbers
    data = path.read_bytes().replace(b"element chunk 3", b"element chunk 2")
    path.write_bytes(data)
    with pytest.raises(SplatFormatError, match=r"a.compressed.ply: compressed PLY: 2 chunks for 600 vertices"):
        read_gaussians(path)


def test_morton_order_degenerate_and_refined():
    from seggaussian.io.compressed_ply import morton_order

    assert morton_order(np.zeros((0, 3))).tolist() == [] and morton_order(np.ones((1, 3))).tolist() == [0]
    assert morton_order(np.ones((600, 3))).tolist() == list(range(600))           # all equal: input order
    # 300 points inside one 10-bit cell of the whole cloud are sorted again over their own bounds
    rng = np.random.default_rng(5)
    cluster = rng.uniform(0, 1e-6, (300, 3))
    points = np.concatenate([cluster, [[1000.0, 1000.0, 1000.0]]])
    order = morton_order(points)
    assert sorted(order.tolist()) == list(range(301)) and order[-1] == 300
    assert order[:300].tolist() == morton_order(cluster).tolist() != list(range(300))
    # a line along x comes out sorted by x
    x = rng.permutation(1000).astype(np.float64)
    line = np.stack([x, np.zeros(1000), np.zeros(1000)], axis=1)
    assert (np.diff(x[morton_order(line)]) > 0).all()


def test_rotation_packing_matches_a_per_record_reference():
    """The vectorised 2+10+10+10 decode against a plain loop over the bits (slow, obviously correct)."""
    from seggaussian.io.compressed_ply import decode_rotations, encode_rotations

    rng = np.random.default_rng(3)
    packed = rng.integers(0, 2**32, 500, dtype=np.uint64).astype(np.uint32)
    fast = decode_rotations(packed)
    for i, value in enumerate(packed.tolist()):
        small = [((value >> s) & 1023) / 1023 for s in (20, 10, 0)]
        small = [(v - 0.5) * np.sqrt(2) for v in small]
        largest = value >> 30
        q, it = [0.0] * 4, iter(small)
        for j in range(4):
            q[j] = np.sqrt(max(0.0, 1 - sum(v * v for v in small))) if j == largest else next(it)
        np.testing.assert_allclose(fast[i], q, atol=1e-6)
    unit = rng.normal(size=(200, 4))
    assert (_quat_error(decode_rotations(encode_rotations(unit)), unit) < np.sqrt(2) / 1023).all()


#: Niantic's RUB -> RDF signs (src/cc/splat-types.h, coordinateConverter with x = 1, y = z = -1), written out:
#: flipQ = (y z, x z, x y) on the quaternion's x, y, z; flipSh = (y, z, x, xy, yz, 1, xz, 1, y, xyz, y, z, x, z, x).
NIANTIC_RUB_TO_RDF_QUAT = (1, 1, -1, -1)            # w, x, y, z
NIANTIC_RUB_TO_RDF_SH = (-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1)


def test_spz_v3_rotations_and_sh_match_a_per_record_reference():
    """The vectorised smallest-three and SH decode against plain loops over the bits and bytes, then RUB -> RDF
    with Niantic's sign tables written out."""
    from seggaussian.io.spz import decode_spz, encode_spz

    rng = np.random.default_rng(4)
    g = _gaussians(n=400, degree=3, seed=4)
    payload = bytearray(gzip.decompress(encode_spz(g, 3)))
    n, k = len(g), 16
    rot_at = 16 + n * (9 + 1 + 3 + 3)
    packed = rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)    # every bit pattern, not only ours
    payload[rot_at: rot_at + 4 * n] = packed.astype("<u4").tobytes()
    fast = decode_spz(bytes(payload))
    sh_bytes = payload[rot_at + 4 * n:]
    for i, value in enumerate(packed.tolist()):
        largest, xyzw, rest = value >> 30, [0.0] * 4, value
        for component in (3, 2, 1, 0):                       # the highest remaining index sits in the lowest bits
            if component == largest:
                continue
            magnitude = (rest & 511) / 511 / np.sqrt(2)
            xyzw[component] = -magnitude if rest & 512 else magnitude
            rest >>= 10
        xyzw[largest] = np.sqrt(max(0.0, 1 - sum(v * v for v in xyzw)))
        expected = np.multiply([xyzw[3], xyzw[0], xyzw[1], xyzw[2]], NIANTIC_RUB_TO_RDF_QUAT)
        np.testing.assert_allclose(fast.quats[i], expected, atol=1e-6)
        for j in range(k - 1):
            for c in range(3):
                raw = (sh_bytes[(i * (k - 1) + j) * 3 + c] - 128) / 128
                assert fast.sh[i, 1 + j, c] == raw * NIANTIC_RUB_TO_RDF_SH[j]


@pytest.mark.parametrize("frame", ["LDB", "RDB", "LUB", "RUB", "LDF", "RDF", "LUF", "RUF"])
def test_spz_frame_signs_follow_the_sh_basis_and_niantics_converter(frame):
    """The signs taking SPZ data stored in ``frame`` to RDF: Niantic's coordinateConverter formulas (flipP, flipQ,
    flipSh of src/cc/splat-types.h, with x, y, z the axis signs), and from the definitions: the rotation matrix of
    the new quaternion is ``F R F``, and the SH basis at ``F d`` is the basis at ``d`` times the SH signs (so a
    colour keeps its value in the new frame)."""
    from seggaussian.frames.axes import axes_to_rdf
    from seggaussian.frames.sh_rotation import sh_basis
    from seggaussian.io.spz import frame_signs
    from seggaussian.core.rotations import quats_to_rotmats

    positions, quats, sh = frame_signs(frame)
    x, y, z = (1 if frame[0] == "R" else -1), (1 if frame[1] == "D" else -1), (1 if frame[2] == "F" else -1)
    assert positions.tolist() == [x, y, z]
    assert quats.tolist() == [1, y * z, x * z, x * y]                         # w is never flipped
    assert sh.tolist() == [y, z, x, x * y, y * z, 1, x * z, 1, y, x * y * z, y, z, x, z, x]
    flip = axes_to_rdf(frame)
    rng = np.random.default_rng(2)
    q = rng.normal(size=(50, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(quats_to_rotmats(q * quats), flip @ quats_to_rotmats(q) @ flip, atol=1e-12)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(sh_basis(d @ flip.T, 3)[:, 1:], sh_basis(d, 3)[:, 1:] * sh, atol=1e-12)


def test_spz_is_written_in_rub_and_read_back_in_rdf():
    """Our writer stores RUB (Niantic's frame): the fixed-point bytes of (1, 2, 3) m are (1, -2, -3) * 4096, the
    quaternion's y and z and the odd-parity SH coefficients are stored negated; the reader undoes it exactly."""
    from seggaussian.io.spz import decode_spz, encode_spz

    sh = np.zeros((1, 4, 3))
    sh[0, 1:, 0] = [0.25, 0.5, -0.75]                              # band 1: -C1 y, C1 z, -C1 x (signs -, -, +)
    g = Gaussians.from_arrays([[1.0, 2.0, 3.0]], [[0.5, 0.5, 0.5, 0.5]], [[-1.0, -2.0, -3.0]], [0.0], sh)
    payload = gzip.decompress(encode_spz(g, 2))
    fixed = np.frombuffer(payload[16:25], np.uint8).reshape(3, 3).astype(np.int64)
    fixed = fixed[:, 0] | (fixed[:, 1] << 8) | (fixed[:, 2] << 16)
    assert ((fixed ^ 0x800000) - 0x800000).tolist() == [4096, -8192, -12288]
    rotation = np.frombuffer(payload[16 + 9 + 1 + 3 + 3: 16 + 9 + 1 + 3 + 3 + 3], np.uint8) / 127.5 - 1
    np.testing.assert_allclose(rotation, [0.5, -0.5, -0.5], atol=1 / 127.5)      # x, y, z with w >= 0
    stored_sh = (np.frombuffer(payload[-9:], np.uint8).reshape(3, 3)[:, 0].astype(np.float64) - 128) / 128
    np.testing.assert_allclose(stored_sh, [-0.25, -0.5, -0.75], atol=0.5 / 128)
    back = decode_spz(encode_spz(g, 2))
    np.testing.assert_allclose(back.means, g.means, atol=0.5 / 4096)
    # version 1 (float16 positions, otherwise v2's layout): the stored RUB (1, -2, -3) reads as (1, 2, 3)
    v1 = payload[:4] + struct.pack("<I", 1) + payload[8:16] + np.array([1, -2, -3], "<f2").tobytes() + payload[25:]
    assert decode_spz(v1).means.tolist() == [[1.0, 2.0, 3.0]]
    np.testing.assert_allclose(back.sh[:, 1:], g.sh[:, 1:], atol=0.5 / 128)
    assert _quat_error(back.quats, g.quats).max() <= 1 / 127.5


@pytest.mark.parametrize("frame", ["RUB", "RDF", "LDB"])
def test_spz_kernels_equal_their_numpy_references_bit_for_bit(frame):
    """The compiled SPZ loops against the numpy references in spz.py: same float32 bits (NaN-free, sign of
    zero included), on every largest index with extreme fields, 24-bit extremes at 0/12/24 fraction bits,
    every SH byte value, and empty inputs; with the signs of SPZ's RUB (the default), of no change and of a frame
    flipping x and z."""
    from seggaussian.io import spz, spz_kernels

    rng = np.random.default_rng(11)
    bits = lambda a: np.ascontiguousarray(a, np.float32).view(np.uint32)  # noqa: E731
    position_signs, quat_signs, sh_signs = spz.frame_signs(frame)
    # smallest-three rotations
    fields = np.array([0, 1, 510, 511, 512, 513, 1022, 1023], np.uint32)
    a, b, c, largest = np.meshgrid(fields, fields, fields, np.arange(4, dtype=np.uint32), indexing="ij")
    edge = (largest << np.uint32(30)) | (c << np.uint32(20)) | (b << np.uint32(10)) | a
    packed = np.concatenate([edge.ravel(), rng.integers(0, 2**32, 50_000, dtype=np.uint64).astype(np.uint32)])
    for words in (packed, packed[:0]):
        out = np.empty((len(words), 4), np.float32)
        spz_kernels.decode_rotations_v3(words, spz._FIELD_DECODE, spz._SLOTS_WXYZ, quat_signs, out)
        np.testing.assert_array_equal(bits(out), bits(spz.decode_rotations_v3_reference(words, quat_signs)))
    # v2 rotations: every byte value in every component
    raw = np.concatenate([np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1),
                          rng.integers(0, 256, (20_000, 3), dtype=np.uint8)])
    for r in (raw, raw[:0]):
        out = np.empty((len(r), 4), np.float32)
        spz_kernels.decode_rotations_v2(r, quat_signs, out)
        np.testing.assert_array_equal(bits(out), bits(spz.decode_rotations_v2_reference(r, quat_signs)))
    # signed 24-bit fixed point positions
    corners = np.array([0, 1, 0x7FFFFF, 0x800000, 0x800001, 0xFFFFFF], np.uint32)
    values = np.concatenate([corners, rng.integers(0, 1 << 24, 30_000).astype(np.uint32)])
    raw = np.stack([values & 255, (values >> 8) & 255, values >> 16], axis=1).astype(np.uint8).ravel()
    n = len(values) // 3
    for fractional_bits in (0, 12, 24):
        out = np.empty((n, 3), np.float32)
        spz_kernels.decode_fixed24(raw, position_signs * np.float32(1.0 / (1 << fractional_bits)), out.reshape(-1))
        np.testing.assert_array_equal(bits(out), bits(spz.decode_fixed24_reference(raw, n, fractional_bits,
                                                                                   position_signs)))
    # 0x800000 (the most negative value) is value 3: point 1's x
    assert spz.decode_fixed24_reference(raw, n, 12, position_signs).reshape(-1)[3] == -2048.0 * position_signs[0]
    # SH rows: every byte value, DC copied as is (negative zero too), degree 0 (no rest bytes), empty
    rest = rng.integers(0, 256, (1000, 45), dtype=np.uint8)
    rest.reshape(-1)[:256] = np.arange(256)
    dc = rng.normal(size=(1000, 3)).astype(np.float32)
    dc[0] = [-0.0, 0.0, np.float32(1e-40)]
    for r, d in ((rest, dc), (rest[:, :0], dc), (rest[:0], dc[:0])):
        out = np.empty((r.shape[0], r.shape[1] + 3), np.float32)
        signs = spz._sh_column_signs(sh_signs, r.shape[1])
        spz_kernels.decode_sh_rows(r, d, spz._SH_BYTE_VALUE, signs, out)
        np.testing.assert_array_equal(bits(out), bits(spz.decode_sh_rows_reference(r, d, signs)))
    if frame == "RUB":                  # the references' default is SPZ's frame
        words = packed[:1000]
        np.testing.assert_array_equal(bits(spz.decode_rotations_v3_reference(words)),
                                      bits(spz.decode_rotations_v3_reference(words, quat_signs)))
        np.testing.assert_array_equal(bits(spz.decode_sh_rows_reference(rest, dc)),
                                      bits(spz.decode_sh_rows_reference(rest, dc, spz._sh_column_signs(sh_signs, 45))))


def test_spz_gzip_streams_libdeflate_and_zlib_agree_and_faults_name_the_problem(monkeypatch):
    """libdeflate's one-call inflate against the plain payload, gzip header fields included; every stream fault
    it refuses (or hides: bytes after the member) reaches zlib's message."""
    import io

    from seggaussian.io import spz
    from seggaussian.io.spz import decode_spz, encode_spz

    g = _gaussians(n=300, degree=2, seed=5)
    data = encode_spz(g, 3)
    payload = gzip.decompress(data)
    named = io.BytesIO()                                   # FNAME and MTIME set, as gzip(1) writes them
    with gzip.GzipFile(filename="scene.spz", mode="wb", fileobj=named, mtime=1) as f:
        f.write(payload)
    plain = decode_spz(payload)
    zlib_path = spz._gunzip_zlib
    monkeypatch.setattr(spz, "_gunzip_zlib", lambda *a: pytest.fail("a valid stream took the zlib path"))
    for stream in (data, named.getvalue(), data + data):   # a repeated member ends in the same trailer: as one
        got = decode_spz(stream)
        for field in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            np.testing.assert_array_equal(getattr(got, field), getattr(plain, field))
    monkeypatch.setattr(spz, "_gunzip_zlib", zlib_path)
    crc, length = struct.unpack("<II", data[-8:])
    for stream, message in ((data + b"xyz", "3 bytes after the gzip stream"),
                            (data[:-5], "truncated gzip stream"),
                            (data[:-8] + struct.pack("<II", crc ^ 1, length), "broken gzip stream"),
                            (data[:-8] + struct.pack("<II", crc, 0xFFFFFFFF), "broken gzip stream"),
                            (data[:-8] + struct.pack("<II", crc, length - 1), "broken gzip stream")):
        with pytest.raises(SplatFormatError, match=message):
            decode_spz(stream, "x.spz")


def test_unknown_and_empty_files_name_the_file(tmp_path):
    for content, message in ((b"", "empty file"), (b"hello world", "unknown splat format"),
                             (gzip.compress(b"ply\nformat ascii 1.0\n"), "gzip file whose content is not SPZ"),
                             (b"\x00" * 31, "not a multiple of 32")):
        path = tmp_path / "x.dat"
        path.write_bytes(content)
        with pytest.raises(SplatFormatError, match=message) as info:
            read_gaussians(path)
        assert str(path) in str(info.value)
    with pytest.raises(SplatFormatError, match="cannot read"):
        read_gaussians(tmp_path / "missing.spz")


def test_splat_nan_payload_is_a_clear_error_or_a_counted_repair(tmp_path):
    g = _gaussians(degree=0, n=20)
    path = tmp_path / "a.splat"
    write_gaussians(path, g)
    data = bytearray(path.read_bytes())
    data[32 * 3 + 12: 32 * 3 + 16] = struct.pack("<f", -1.0)         # a negative scale: log -> NaN
    path.write_bytes(bytes(data))
    with pytest.raises(SplatFormatError, match=r"a.splat \(antimatter15 .splat\): invalid values .*scale_0"):
        read_gaussians(path)
    repaired, report, _ = read_gaussians(path, on_invalid="repair")
    assert len(repaired) == 19 and report.num_dropped == 1


def test_output_format_from_name_and_stem():
    assert format_for_output("a/b.compressed.ply") == "compressed_ply"
    assert [format_for_output(f"x{s}") for s in (".ply", ".splat", ".spz", ".PLY")] == ["ply", "splat", "spz", "ply"]
    assert format_for_output("x.ply", "spz") == "spz"
    assert format_for_output("x.KSPLAT") == "ksplat"
    with pytest.raises(ValueError, match="unknown splat format"):
        format_for_output("x.ply", "sog")
    assert [format_for_output(f"x{s}") for s in (".glb", ".GLTF")] == ["gltf", "gltf"]
    assert [scene_stem(p) for p in ("r.compressed.ply", "r.ply", "r.spz", "r.splat", "r.ksplat", "r.glb",
                                    "r.gltf")] == ["r"] * 7
    assert set(FORMATS) == {"ply", "compressed_ply", "splat", "spz", "ksplat", "gltf"}


# ---------------------------------------------------------------------------------------------
# palette and legend
# ---------------------------------------------------------------------------------------------
def test_palette_is_fixed_and_documented():
    import colorsys

    from seggaussian.labels.palette import IGNORE_RGB, label_colours, palette

    colours = palette(100)
    assert len({tuple(c) for c in colours}) == 100                    # 100 distinct class colours
    for i in (0, 1, 7, 99, 1234):
        r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1, 0.75, 0.95 if i % 2 == 0 else 0.7)
        np.testing.assert_array_equal(label_colours(np.array([i]))[0], np.round(np.array([r, g, b]) * 255))
    assert tuple(label_colours(np.array([IGNORE_LABEL]))[0]) == IGNORE_RGB
    assert tuple(label_colours(np.array([-1]))[0]) == IGNORE_RGB
    assert tuple(colours[0]) == (242, 61, 61)                            # the documented rule, pinned


def test_colour_by_labels_and_legend(tmp_path):
    from seggaussian.labels.palette import build_legend, colour_by_labels, label_colours, legend_paths, write_legend

    g = _gaussians(n=50, degree=3).with_extras(semantic=np.r_[np.zeros(20), np.ones(25), np.full(5, IGNORE_LABEL)]
                                               .astype(np.int32))
    painted = colour_by_labels(g, g.extras["semantic"])
    rgb = label_colours(g.extras["semantic"]).astype(np.float32) / 255
    np.testing.assert_allclose(painted.sh[:, 0], (rgb - 0.5) / SH_C0, rtol=1e-6)
    assert painted.sh.shape == g.sh.shape and not painted.sh[:, 1:].any()
    np.testing.assert_array_equal(painted.extras["semantic"], g.extras["semantic"])
    np.testing.assert_array_equal(painted.means, g.means)
    legend = build_legend(g.extras["semantic"], "semantic", ["wall", "floor"])
    assert [(e.id, e.name, e.count) for e in legend.entries] == [(0, "wall", 20), (1, "floor", 25),
                                                                  (IGNORE_LABEL, "ignore", 5)]
    out = tmp_path / "scene.ply"
    json_path, png_path = write_legend(out, legend)
    assert (json_path, png_path) == legend_paths(out) == (tmp_path / "scene.legend.json", tmp_path / "scene.legend.png")
    doc = json.loads(json_path.read_text())
    assert doc["entries"][1] == {"id": 1, "name": "floor", "rgb": label_colours(np.array([1]))[0].tolist(), "count": 25}
    import cv2

    image = cv2.imread(str(png_path))
    assert image is not None and image.shape[0] > 3 * 22
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.legend.json", "scene.legend.png"]


# ---------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------
def test_cli_inspect_names_the_format_and_import_converts(tmp_path):
    from cli.seggaussian_cli import main
    from seggaussian.io.ply.reader import read_gaussians_ply

    g = _gaussians(degree=1)
    runner = CliRunner()
    for name, fmt in (("s.compressed.ply", "compressed_ply"), ("s.splat", "splat"), ("s.spz", "spz")):
        src = tmp_path / name
        write_gaussians(src, g if fmt != "splat" else _gaussians(degree=0))
        result = runner.invoke(main, ["inspect", str(src), "--json"])
        assert result.exit_code == 0, result.output
        info = json.loads(result.output)
        assert info["file_format"] == fmt and info["num_gaussians"] == len(g)
        text = runner.invoke(main, ["inspect", str(src)]).output
        assert info["format_title"] in text.splitlines()[-1]
        out = tmp_path / f"imported_{fmt}"
        result = runner.invoke(main, ["import", str(src), "--out", str(out), "--json"])
        assert result.exit_code == 0, result.output
        payload = json.loads(result.output)
        assert payload["format"] == fmt and payload["ply"].endswith("/s.ply")
        ply, report = read_gaussians_ply(out / "s.ply")
        decoded, _ = read_gaussians_raw(src)
        np.testing.assert_array_equal(ply.means, decoded.means)
        np.testing.assert_array_equal(ply.sh, decoded.sh)
    bad = tmp_path / "bad.spz"
    bad.write_bytes(b"NGSP" + bytes(20))
    result = runner.invoke(main, ["import", str(bad), "--out", str(tmp_path / "o")])
    assert result.exit_code != 0 and "bad.spz" in result.output and "Traceback" not in result.output


# ---------------------------------------------------------------------------------------------
# .ksplat: multi-section files against a per-record reference decoder
# ---------------------------------------------------------------------------------------------
def _ksplat_slow_decode(data: bytes) -> dict[str, np.ndarray]:
    """A per-splat loop over the file, written from the format description (slow, obviously correct)."""
    from seggaussian.io.ksplat import SH_VALUES

    u8, u16, u32, f32 = (lambda o: data[o]), (lambda o: struct.unpack_from("<H", data, o)[0]), \
        (lambda o: struct.unpack_from("<I", data, o)[0]), (lambda o: struct.unpack_from("<f", data, o)[0])
    f16 = lambda o: float(np.frombuffer(data, "<f2", 1, o)[0])  # noqa: E731
    max_sections, level = u32(4), u16(20)
    sh_min, sh_max = f32(36) or -1.5, f32(40) or 1.5
    out = {"means": [], "scales": [], "quats": [], "rgba": [], "rest": []}
    base = 4096 + 1024 * max_sections
    for s in range(max_sections):
        h = 4096 + 1024 * s
        count, room, capacity, buckets = u32(h), u32(h + 4), u32(h + 8), u32(h + 12)
        block, bucket_bytes, q_range = f32(h + 16), u16(h + 20), u32(h + 24) or (1 if level == 0 else 32767)
        full, partial, degree = u32(h + 32), u32(h + 36), u16(h + 40)
        m = SH_VALUES[degree]
        per = (44 if level == 0 else 24) + m * (4, 2, 1)[level]
        records = base + 4 * partial + bucket_bytes * buckets
        bucket, bucket_end = -1, 0
        for i in range(count):
            while level and i >= bucket_end:                 # walk the buckets: full ones, then the partial ones
                bucket += 1
                bucket_end += capacity if bucket < full else u32(base + 4 * (bucket - full))
            o = records + i * per
            if level == 0:
                xyz = [f32(o + 4 * k) for k in range(3)]
                scale = [f32(o + 12 + 4 * k) for k in range(3)]
                quat = [f32(o + 24 + 4 * k) for k in range(4)]
                c = o + 40
            else:
                centre = [f32(base + 4 * partial + 12 * bucket + 4 * k) for k in range(3)]
                xyz = [(u16(o + 2 * k) - q_range) * block / 2 / q_range + centre[k] for k in range(3)]
                scale = [f16(o + 6 + 2 * k) for k in range(3)]
                quat = [f16(o + 12 + 2 * k) for k in range(4)]
                c = o + 20
            rest = np.zeros((15, 3))
            for j in range(m):
                band = 1 if j < 9 else 2 if j < 24 else 3
                first = {1: 0, 2: 9, 3: 24}[band]
                width = 2 * band + 1
                channel, coeff = (j - first) // width, band * band - 1 + (j - first) % width
                p = c + 4
                v = (f32(p + 4 * j) if level == 0 else f16(p + 2 * j) if level == 1
                     else sh_min + u8(p + j) / 255 * (sh_max - sh_min))
                rest[coeff, channel] = v
            out["means"].append(xyz)
            out["scales"].append(scale)
            out["quats"].append(quat)
            out["rgba"].append([u8(c + k) for k in range(4)])
            out["rest"].append(rest)
        base = records + per * room
    return {k: np.array(v, np.float64) for k, v in out.items()}


def _two_section_ksplat(level: int) -> bytes:
    """Two sections of our writer (SH degrees 1 and 2), the second with room for 50 more splats (padding)."""
    from seggaussian.io.ksplat import encode_ksplat

    a = encode_ksplat(_gaussians(n=700, degree=1, seed=1), level)         # 700: two full buckets and partials
    b = encode_ksplat(_gaussians(n=90, degree=2, seed=2), level)
    main = bytearray(a[:4096])
    struct.pack_into("<III", main, 4, 2, 2, 790)
    struct.pack_into("<I", main, 16, 790)
    if level == 2:                                           # one SH range for the file: take the wider one
        struct.pack_into("<ff", main, 36, *max((struct.unpack_from("<ff", x, 36) for x in (a, b)),
                                               key=lambda r: r[1]))
    head_b = bytearray(b[4096:5120])
    struct.pack_into("<I", head_b, 4, 140)                   # room for 140 splats, 90 used
    per = (len(b) - 5120 - (struct.unpack_from("<I", b, 4096 + 36)[0] * 4
                            + 12 * struct.unpack_from("<I", b, 4096 + 12)[0])) // 90
    return bytes(main) + a[4096:5120] + bytes(head_b) + a[5120:] + b[5120:] + bytes(50 * per)


@pytest.mark.parametrize("level", [0, 1, 2])
def test_ksplat_vectorised_decode_equals_a_per_record_reference(level):
    from seggaussian.io.ksplat import decode_ksplat

    data = _two_section_ksplat(level)
    fast = decode_ksplat(data, "two.ksplat")
    slow = _ksplat_slow_decode(data)
    assert len(fast) == 790 and fast.sh_degree == 2               # the highest degree of the sections
    np.testing.assert_allclose(fast.means, slow["means"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.log_scales, np.log(slow["scales"]), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(fast.quats, slow["quats"], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(fast.dc_colors(), slow["rgba"][:, :3] / 255, atol=1e-6)
    np.testing.assert_allclose(fast.opacities(), np.clip(slow["rgba"][:, 3] / 255, 1e-6, 1 - 1e-6), atol=1e-6)
    np.testing.assert_allclose(fast.sh[:, 1:], slow["rest"][:, :8], rtol=1e-6, atol=1e-6)
    assert (fast.sh[:700, 4:] == 0).all()                          # the degree-1 section has no band 2


def test_ksplat_errors_and_edge_cases(tmp_path):
    from seggaussian.io.ksplat import ZERO_SCALE_LOG, bucket_layout, decode_ksplat, encode_ksplat

    g = _gaussians(n=300, degree=1)
    data = bytearray(encode_ksplat(g, 1))
    # a zero (float16-underflowed) scale decodes to the reference's floor, a negative one is left for validation
    first = 5120 + 4 * struct.unpack_from("<I", data, 4096 + 36)[0] + 12 * struct.unpack_from("<I", data, 4096 + 12)[0]
    data[first + 6: first + 8] = bytes(2)
    data[first + 42 + 6: first + 42 + 8] = np.array([-1.0], "<f2").tobytes()    # 42 bytes per record
    with np.errstate(invalid="ignore"):
        back = decode_ksplat(bytes(data))
    assert back.log_scales[0, 0] == ZERO_SCALE_LOG and np.isnan(back.log_scales[1, 0])
    path = tmp_path / "neg.ksplat"
    path.write_bytes(bytes(data))
    with pytest.raises(SplatFormatError, match=r"neg.ksplat \(mkkellogg .ksplat\): invalid values .*scale_0"):
        read_gaussians(path)
    # truncated, trailing bytes, counts that do not add up, bad level: one line naming the file
    cases = {"truncated": bytes(data[:-10]), "after the last section": bytes(data) + b"\0" * 8,
             "the header declares": bytes(data[:16]) + struct.pack("<I", 301) + bytes(data[20:]),
             "do not cover": bytes(data[:5120]) + struct.pack("<I", 0) + bytes(data[5124:])}   # a partial bucket
    for message, content in cases.items():
        path.write_bytes(content)
        with pytest.raises(SplatFormatError, match=message) as info:
            read_gaussians(path)
        assert str(path) in str(info.value) and "\n" not in str(info.value)
    # an empty scene writes and reads; every splat lands in a bucket within half a block of its centre
    empty = Gaussians.from_arrays(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0),
                                  np.zeros((0, 1, 3)))
    assert len(decode_ksplat(encode_ksplat(empty, 1))) == 0
    layout = bucket_layout(g.means, block_size=1.0, capacity=4)
    assert sorted(layout.order.tolist()) == list(range(len(g)))
    sizes = np.concatenate([np.full(layout.full, 4), layout.partial_sizes])
    assert (layout.partial_sizes < 4).all() and sizes.sum() == len(g)
    centre_of = np.repeat(layout.centres, sizes, axis=0)
    assert (np.abs(g.means[layout.order] - centre_of) <= 0.5 + 1e-6).all()
