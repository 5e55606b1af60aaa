"""SPZ against its author's implementation: Niantic's library (github.com/nianticlabs/spz) in its WebAssembly build
@adobe/spz (npm, "Niantic Labs & Adobe"), driven by niantic_spz.mjs beside this file.

``make setup`` installs @adobe/spz (pinned in the Makefile) into ``.node/`` where node and npm exist; without it
these tests skip with the reason. All of Niantic's loads and saves run in one node process (a module fixture).

The frame rule under test (seggaussian/io/spz.py): SPZ stores RUB, ``Gaussians`` hold RDF. Niantic's library takes
the frame of the caller's data as an argument (``PackOptions.from``, ``UnpackOptions.to``), so it is asked for RDF
in both directions and must agree with us without any sign fixed by hand here; asked for no conversion
(``UNSPECIFIED``) it returns the stored RUB values, which must be ours under ``P = diag(1, -1, -1)``.

Directions, for every version we write (2, 3, 4) and SH degrees 0..3:

* our writer's files -> Niantic's reader: equal to our reader's decode of the same bytes (float32 rounding), and
  to the Gaussians written within the quantisation steps;
* Niantic's writer (``from: RDF``, 8-bit SH) -> our reader: equal to Niantic's own decode of the same bytes, and to
  the Gaussians given to it within the steps;
* a real capture (biker.spz, playcanvas/engine) and v4 files carrying the SPZ_ADOBE_coordinate_system extension
  (every standard-family frame): our decode equals Niantic's. In v1-3 files the extension records follow the SH
  block; Niantic's reader (0.2.3) cannot read them there (its in-memory stream reports no remaining bytes:
  "[SPZ ERROR] tryParseExtension: byteLength 8 exceeds remaining stream bytes", and the records are dropped),
  so our reading of those is checked against the v4 file's instead.
"""

from __future__ import annotations

import gzip
import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_splat_reference import (DECODE_ATOL, QUAT_DECODE_ATOL, _sign_free_quat_error, _skip_without_web_data,
                                  _web_splats, apply_p, make_gaussians)

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians_raw
from seggaussian.io.spz import (COORDINATE_SYSTEM_EXTENSION, COORDINATE_SYSTEMS, V4_HEADER, decode_spz, encode_spz)
from seggaussian.io.splat_common import SplatFormatError

ROOT = Path(__file__).resolve().parents[3]
DRIVER = Path(__file__).resolve().with_name("niantic_spz.mjs")
NIANTIC_MODULE = ROOT / ".node" / "node_modules" / "@adobe" / "spz" / "dist" / "spz.js"
VERSIONS = (2, 3, 4)
DEGREES = (0, 1, 2, 3)
#: Niantic's writer quantises SH band 1 to 5 bits and bands 2+ to 4 bits by default; 8 bits keeps the byte step.
SH_BITS = 8
#: Quantisation steps of SPZ (seggaussian/io/spz.py): half of each bounds the error of one write.
POSITION_HALF_STEP = 0.5 / 4096                     # 12 fraction bits, as both writers use
LOG_SCALE_HALF_STEP = 0.5 / 16
OPACITY_HALF_STEP = 0.5 / 255
DC_HALF_STEP = 0.5 / (255 * 0.15)
SH_HALF_STEP = 0.5 / 128
#: v3+ smallest three: one component step is 1 / (511 sqrt 2); the derived largest one carries the others'
#: rounding, so a whole-quaternion bound of two steps (as test_splat_reference uses).
QUAT_BOUND_V3 = 2 / (511 * np.sqrt(2))
#: v2: x, y, z each within one byte step of the unit quaternion with w >= 0 (w itself is derived).
QUAT_XYZ_BOUND_V2 = 1 / 127.5
#: SPZ's log-scale byte covers [-10, 15.9375]; both writers clamp to it.
LOG_SCALE_RANGE = (-10.0, 255 / 16 - 10)
#: Slack for float32 arithmetic on values of order 1 in the step comparisons.
FLOAT_SLACK = 1e-5
#: An extension type no reader knows: skipped by Niantic's library and by ours.
UNKNOWN_EXTENSION = 0x12340001
#: Standard-family frame codes of the coordinate-system extension (0 = UNSPECIFIED, read as RUB) and one rotated.
STANDARD_FRAME_CODES = tuple(range(0, 9))
ROTATED_FRAME_CODE = 12                               # RFU

needs_niantic = pytest.mark.skipif(
    shutil.which("node") is None or not NIANTIC_MODULE.is_file(),
    reason=f"Niantic's SPZ library (@adobe/spz) not installed ({NIANTIC_MODULE} missing or no node); "
           "run `make setup` with node/npm")

ATTRIBUTES = ("positions", "scales", "rotations", "alphas", "colors", "sh")


def dump_cloud(g: Gaussians, prefix: Path) -> None:
    """``g`` in Niantic's GaussianCloud layout (rotations x, y, z, w; SH without the DC, channel innermost)."""
    prefix.with_name(prefix.name + ".json").write_text(json.dumps(
        {"numPoints": len(g), "shDegree": g.sh_degree, "antialiased": False}))
    arrays = {"positions": g.means, "scales": g.log_scales, "rotations": g.quats[:, [1, 2, 3, 0]],
              "alphas": g.opacity_logits, "colors": g.sh[:, 0], "sh": g.sh[:, 1:]}
    for name in ATTRIBUTES:
        np.ascontiguousarray(arrays[name], "<f4").tofile(prefix.with_name(f"{prefix.name}.{name}.f32"))


def load_cloud(prefix: Path) -> Gaussians:
    """A GaussianCloud written by the driver -> ``Gaussians`` (no value changed but the quaternion order)."""
    meta = json.loads(prefix.with_name(prefix.name + ".json").read_text())
    n, k = meta["numPoints"], (meta["shDegree"] + 1) ** 2
    a = {name: np.fromfile(prefix.with_name(f"{prefix.name}.{name}.f32"), "<f4") for name in ATTRIBUTES}
    sh = np.concatenate([a["colors"].reshape(n, 1, 3), a["sh"].reshape(n, k - 1, 3)], axis=1)
    return Gaussians.from_arrays(a["positions"].reshape(n, 3), a["rotations"].reshape(n, 4)[:, [3, 0, 1, 2]],
                                 a["scales"].reshape(n, 3), a["alphas"], sh)


def with_coordinate_extension(data: bytes, code: int) -> bytes:
    """Our SPZ file with extension records added: an unknown one, then SPZ_ADOBE_coordinate_system naming frame
    ``code`` (the stored bytes unchanged, so both readers must now take them as that frame). v4: between the
    header and the table of contents; v2-3: after the SH block of the gzip payload. Header flag 2 set."""
    records = (struct.pack("<II", UNKNOWN_EXTENSION, 8) + bytes(range(8))
               + struct.pack("<III", COORDINATE_SYSTEM_EXTENSION, 4, code))
    if data[:4] == b"NGSP":
        header = bytearray(data[:V4_HEADER.size])
        header[14] |= 2
        struct.pack_into("<I", header, 16, V4_HEADER.size + len(records))
        return bytes(header) + records + data[V4_HEADER.size:]
    payload = bytearray(gzip.decompress(data))
    payload[14] |= 2
    return gzip.compress(bytes(payload) + records, mtime=0)


@pytest.fixture(scope="module")
def niantic(tmp_path_factory):
    """Every file of the comparison and Niantic's decodes of them, from one run of the driver."""
    if shutil.which("node") is None or not NIANTIC_MODULE.is_file():
        pytest.skip(f"Niantic's SPZ library (@adobe/spz) not installed ({NIANTIC_MODULE}); run `make setup`")
    d = tmp_path_factory.mktemp("niantic_spz")
    sources, files, jobs = {}, {}, []

    def load(key: str, path: Path, to: str) -> None:
        files[key] = path
        jobs.append({"op": "load", "in": str(path), "out": str(d / f"{key}.{to}"), "to": to})

    for degree in DEGREES:
        g = make_gaussians(degree, seed=100 + degree)
        sources[degree] = g
        dump_cloud(g, d / f"src{degree}")
        for version in VERSIONS:
            ours = d / f"ours_v{version}_sh{degree}.spz"
            ours.write_bytes(encode_spz(g, version))
            load(f"ours_v{version}_sh{degree}", ours, "RDF")
            load(f"ours_v{version}_sh{degree}", ours, "UNSPECIFIED")
            theirs = d / f"niantic_v{version}_sh{degree}.spz"
            jobs.append({"op": "save", "in": str(d / f"src{degree}"), "out": str(theirs), "version": version,
                         "from": "RDF", "sh1Bits": SH_BITS, "shRestBits": SH_BITS})
            load(f"niantic_v{version}_sh{degree}", theirs, "RDF")
    for code in STANDARD_FRAME_CODES:
        path = d / f"ext_v4_{code}.spz"
        path.write_bytes(with_coordinate_extension(encode_spz(sources[2], 4), code))
        load(f"ext_v4_{code}", path, "RDF")
    web = _web_splats()
    if web is not None and (web / "biker.spz").is_file():
        load("biker", web / "biker.spz", "RDF")
    (d / "jobs.json").write_text(json.dumps(jobs))
    result = subprocess.run(["node", str(DRIVER), str(NIANTIC_MODULE), str(d / "jobs.json")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"niantic_spz.mjs: {result.stderr[-3000:]}"

    def decoded(key: str, to: str = "RDF") -> Gaussians:
        return load_cloud(d / f"{key}.{to}")

    return sources, files, decoded


def assert_same_decode(ours: Gaussians, theirs: Gaussians, what: str) -> None:
    """Two decoders of the same bytes: equal up to float32 rounding (opacities compared, since Niantic's logit of
    the bytes 0 and 255 is infinite where ours is clamped)."""
    assert len(ours) == len(theirs) and ours.sh_degree == theirs.sh_degree, what
    np.testing.assert_allclose(ours.means, theirs.means, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.log_scales, theirs.log_scales, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.sh, theirs.sh, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.opacities(), theirs.opacities(), atol=DECODE_ATOL, err_msg=what)
    assert _sign_free_quat_error(ours.quats, theirs.quats).max() < QUAT_DECODE_ATOL, what


def assert_within_steps(decoded: Gaussians, original: Gaussians, version: int, what: str) -> None:
    """``decoded`` (RDF) within SPZ's quantisation steps of the Gaussians ``original`` that were written."""
    assert np.abs(decoded.means - original.means).max() <= POSITION_HALF_STEP + 1e-6, what
    clamped = np.clip(original.log_scales, *LOG_SCALE_RANGE)
    assert np.abs(decoded.log_scales - clamped).max() <= LOG_SCALE_HALF_STEP + FLOAT_SLACK, what
    assert np.abs(decoded.opacities() - original.opacities()).max() <= OPACITY_HALF_STEP + 1e-6, what
    assert np.abs(decoded.sh[:, 0] - original.sh[:, 0]).max() <= DC_HALF_STEP + FLOAT_SLACK, what
    if original.sh_degree:
        assert np.abs(decoded.sh[:, 1:] - original.sh[:, 1:]).max() <= SH_HALF_STEP + FLOAT_SLACK, what
    if version == 2:
        unit = original.normalized_quats().astype(np.float64)
        unit *= np.where(unit[:, :1] < 0, -1.0, 1.0)
        assert np.abs(decoded.quats[:, 1:] - unit[:, 1:]).max() <= QUAT_XYZ_BOUND_V2 + FLOAT_SLACK, what
    else:
        assert _sign_free_quat_error(decoded.quats, original.quats).max() <= QUAT_BOUND_V3 + FLOAT_SLACK, what


@needs_niantic
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("version", VERSIONS)
def test_our_spz_files_are_read_by_niantic(niantic, version, degree):
    sources, files, decoded = niantic
    key = f"ours_v{version}_sh{degree}"
    ours = decode_spz(files[key].read_bytes())
    assert_same_decode(ours, decoded(key, "RDF"), f"{key}: Niantic's reader asked for RDF")
    # the bytes hold RUB: Niantic's decode without conversion is ours under P
    assert_same_decode(apply_p(ours), decoded(key, "UNSPECIFIED"), f"{key}: Niantic's reader, no conversion")
    assert_within_steps(decoded(key, "RDF"), sources[degree], version, key)


@needs_niantic
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("version", VERSIONS)
def test_niantic_spz_files_are_read_by_us(niantic, version, degree):
    sources, files, decoded = niantic
    key = f"niantic_v{version}_sh{degree}"
    data = files[key].read_bytes()
    assert data.startswith(b"\x1f\x8b" if version < 4 else b"NGSP")
    ours, fmt = read_gaussians_raw(files[key])
    assert fmt == "spz"
    assert_same_decode(ours, decoded(key), f"{key}: our reader against Niantic's")
    assert_within_steps(ours, sources[degree], version, key)


@needs_niantic
def test_a_real_capture_decodes_like_niantic(niantic):
    """biker.spz (playcanvas/engine, SPZ v4, 152,746 Gaussians): our decode equals Niantic's RDF decode."""
    _, files, decoded = niantic
    if "biker" not in files:
        _skip_without_web_data("biker.spz", "a capture from playcanvas/engine")
    ours, _ = read_gaussians_raw(files["biker"])
    assert len(ours) == 152_746
    assert_same_decode(ours, decoded("biker"), "biker.spz")


@needs_niantic
@pytest.mark.parametrize("code", STANDARD_FRAME_CODES)
def test_coordinate_system_extension_is_read_like_niantic(niantic, code):
    """A v4 file whose SPZ_ADOBE_coordinate_system extension (after an unknown record, skipped by both) names a
    standard-family frame (0 = UNSPECIFIED, read as RUB by Niantic): both readers take the stored values as that
    frame and convert them to RDF alike; the same records after the SH block of a v3 file are read the same way."""
    sources, files, decoded = niantic
    key = f"ext_v4_{code}"
    ours = decode_spz(files[key].read_bytes(), key)
    frame = COORDINATE_SYSTEMS[code]
    assert_same_decode(ours, decoded(key), f"{key} ({frame})")
    # the extension is obeyed: the stored values (RUB values of the Gaussians: P of the plain decode) taken as
    # ``frame``, whose letters give each axis's sign in RDF
    stored = apply_p(decode_spz(encode_spz(sources[2], 4))).means
    signs = np.array([1 if frame[0] == "R" else -1, 1 if frame[1] == "D" else -1, 1 if frame[2] == "F" else -1])
    np.testing.assert_array_equal(ours.means, stored * signs)
    legacy = decode_spz(with_coordinate_extension(encode_spz(sources[2], 3), code), "v3")
    for name in ("means", "log_scales", "opacity_logits", "sh"):     # v3 and v4 quantise alike
        np.testing.assert_array_equal(getattr(legacy, name), getattr(ours, name))
    assert _sign_free_quat_error(legacy.quats, ours.quats).max() == 0


def test_rotated_frames_and_broken_extension_records_are_refused():
    """Frames of Niantic's rotated family (y and z exchanged) are not read; malformed records name the problem.
    Needs no reference: the files are assembled here."""
    g = make_gaussians(1, seed=7, n=20)
    for version in (3, 4):
        data = with_coordinate_extension(encode_spz(g, version), ROTATED_FRAME_CODE)
        with pytest.raises(SplatFormatError, match=r"x.spz: Niantic SPZ: stored in the rotated frame RFU"):
            decode_spz(data, "x.spz")
        with pytest.raises(SplatFormatError, match=r"unknown frame code 17"):
            decode_spz(with_coordinate_extension(encode_spz(g, version), 17), "x.spz")
    v4 = bytearray(with_coordinate_extension(encode_spz(g, 4), 6))
    struct.pack_into("<I", v4, V4_HEADER.size + 4, 200)            # the unknown record claims 200 bytes
    with pytest.raises(SplatFormatError, match=r"extension 0x12340001 declares 200 bytes, only \d+ remain"):
        decode_spz(bytes(v4), "x.spz")
    # stored as RDF (code 6): read without conversion, the raw values of our RUB file
    raw_rdf = decode_spz(with_coordinate_extension(encode_spz(g, 4), 6))
    np.testing.assert_array_equal(raw_rdf.means, apply_p(decode_spz(encode_spz(g, 4))).means)
