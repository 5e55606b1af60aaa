""".ksplat against its author's implementation: GaussianSplats3D (@mkkellogg/gaussian-splats-3d, npm), driven
headless in node by gs3d_ksplat.mjs beside this file (its SplatBuffer reads, its PlyLoader writes, as its
util/create-ksplat.js does; three.js is its peer dependency). antimatter15's .splat has no package; GaussianSplats3D's
SplatParser reads it (w at byte 28, as antimatter15's viewer), and reads our .splat files alike.

``make setup`` installs both (pinned in the Makefile) into ``.node/`` where node and npm exist; without them these
tests skip with the reason. All of GaussianSplats3D's work runs in one node process (a module fixture).

GaussianSplats3D reads SH up to degree 2, so degrees 0..2 at compression levels 0, 1, 2:

* our writer's files -> GaussianSplats3D's decode equals ours (the same bytes: float32 rounding);
* GaussianSplats3D's files, written from a PLY of the test's Gaussians -> our decode equals its own, and the test's
  Gaussians (matched by position: its writer regroups splats into buckets) within one step of each grid (its
  writer truncates to the byte, float16 and bucket grids where ours rounds).

Not compared: the reference converter's fixture minimal.ksplat, which GaussianSplats3D reads as empty (its header
declares 0 sections and 0 maximum splats at bytes 8 and 12; the reference converter and we read its one section
table regardless).

Frame: .ksplat and .splat store the PLY's values as they are (RDF, no conversion in either direction), as both
readers agree here.
"""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
from test_splat_reference import DECODE_ATOL, QUAT_DECODE_ATOL, _sign_free_quat_error, make_gaussians

from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians_raw
from seggaussian.io.ksplat import BLOCK_SIZE, DEFAULT_RANGE, write_ksplat
from seggaussian.io.ply.writer import write_gaussians_ply
from seggaussian.io.splat import write_splat
from seggaussian.io.splat_common import logit_from_unit

ROOT = Path(__file__).resolve().parents[3]
DRIVER = Path(__file__).resolve().with_name("gs3d_ksplat.mjs")
GS3D_MODULE = (ROOT / ".node" / "node_modules" / "@mkkellogg" / "gaussian-splats-3d" / "build"
               / "gaussian-splats-3d.module.js")
LEVELS = (0, 1, 2)
DEGREES = (0, 1, 2)                 # GaussianSplats3D's SplatBuffer stops at SH degree 2
#: Grids of the levels (seggaussian/io/ksplat.py): colour and opacity bytes; float16 (levels 1-2: scales,
#: rotations, level-1 SH) with a relative step of 2^-10 (GaussianSplats3D's writer truncates: a whole step); bucket
#: positions ``block / 2 / range``; level-2 SH bytes over the header's SH range (f32 sh_min, sh_max at byte 36).
BYTE_STEP = 1 / 255
HALF16_RELATIVE_STEP = 2.0 ** -10
POSITION_STEP = {0: 0.0, 1: BLOCK_SIZE / 2 / DEFAULT_RANGE[1], 2: BLOCK_SIZE / 2 / DEFAULT_RANGE[2]}
SH_RANGE_OFFSET = 36
#: float16's smallest subnormal: scales below it underflow to 0 at levels 1-2.
HALF16_SUBNORMAL = 2.0 ** -24
#: Float32 rounding, relative, of the level-0 values and of the bucket centres' arithmetic.
FLOAT32_RELATIVE = 1e-6
#: Slack for float32 arithmetic on values of order 1 in the step comparisons.
FLOAT_SLACK = 1e-5
#: .splat quaternion components are bytes: one step of 1/127.5 (1/128 as GaussianSplats3D decodes them).
SPLAT_QUAT_BYTE_STEP = 1 / 127.5

needs_gs3d = pytest.mark.skipif(
    shutil.which("node") is None or not GS3D_MODULE.is_file(),
    reason=f"GaussianSplats3D not installed ({GS3D_MODULE} missing or no node); run `make setup` with node/npm")


def load_decode(prefix: Path) -> Gaussians:
    """The driver's decode -> ``Gaussians`` (log of the linear scales, colour and opacity bytes to f_dc and logits)."""
    meta = json.loads(prefix.with_name(prefix.name + ".json").read_text())
    n, k = meta["count"], (meta["shDegree"] + 1) ** 2
    read = lambda name, dtype: np.fromfile(prefix.with_name(f"{prefix.name}.{name}"), dtype)  # noqa: E731
    colors = read("colors.u8", np.uint8).reshape(n, 4).astype(np.float64) / 255
    sh = np.concatenate([((colors[:, :3] - 0.5) / 0.28209479177387814)[:, None, :],
                         read("sh.f32", "<f4").reshape(n, k - 1, 3)], axis=1)
    return Gaussians.from_arrays(read("centers.f32", "<f4").reshape(n, 3),
                                 read("rotations.f32", "<f4").reshape(n, 4)[:, [3, 0, 1, 2]],
                                 np.log(read("scales.f32", "<f4").reshape(n, 3).astype(np.float64)),
                                 logit_from_unit(colors[:, 3]), sh)


@pytest.fixture(scope="module")
def gs3d(tmp_path_factory):
    """Every file of the comparison and GaussianSplats3D's decodes of them, from one run of the driver."""
    if shutil.which("node") is None or not GS3D_MODULE.is_file():
        pytest.skip(f"GaussianSplats3D not installed ({GS3D_MODULE}); run `make setup` with node/npm")
    d = tmp_path_factory.mktemp("gs3d_ksplat")
    sources, files, jobs = {}, {}, []
    for degree in DEGREES:
        g = make_gaussians(degree, seed=200 + degree)
        sources[degree] = g
        write_gaussians_ply(d / f"src{degree}.ply", g)
        for level in LEVELS:
            ours = d / f"ours_l{level}_sh{degree}.ksplat"
            write_ksplat(ours, g, compression_level=level)
            theirs = d / f"gs3d_l{level}_sh{degree}.ksplat"
            jobs.append({"op": "encode", "in": str(d / f"src{degree}.ply"), "out": str(theirs), "level": level,
                         "shDegree": degree})
            for key, path in ((ours.stem, ours), (theirs.stem, theirs)):
                files[key] = path
                jobs.append({"op": "decode", "in": str(path), "out": str(d / key)})
    splat = d / "ours.splat"
    write_splat(splat, sources[0])
    files["ours_splat"] = splat
    jobs.append({"op": "decode_splat", "in": str(splat), "out": str(d / "ours_splat")})
    (d / "jobs.json").write_text(json.dumps(jobs))
    result = subprocess.run(["node", str(DRIVER), str(GS3D_MODULE), str(d / "jobs.json")],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"gs3d_ksplat.mjs: {result.stderr[-3000:]}"
    return sources, files, lambda key: load_decode(d / key)


def assert_same_decode(ours: Gaussians, theirs: Gaussians, what: str) -> None:
    """Two decoders of the same bytes: equal up to float32 rounding (colour and opacity compared as the bytes'
    values: our logits are clamped at the bytes 0 and 255)."""
    assert len(ours) == len(theirs) and ours.sh_degree == theirs.sh_degree, what
    atol = max(DECODE_ATOL, 8 * float(np.finfo(np.float32).eps) * float(np.abs(theirs.means).max(initial=0)))
    np.testing.assert_allclose(ours.means, theirs.means, atol=atol, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.log_scales, theirs.log_scales, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.sh, theirs.sh, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.opacities(), theirs.opacities(), atol=DECODE_ATOL, err_msg=what)
    assert _sign_free_quat_error(ours.quats, theirs.quats).max() < QUAT_DECODE_ATOL, what


@needs_gs3d
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("level", LEVELS)
def test_our_ksplat_files_decode_like_gaussiansplats3d(gs3d, level, degree):
    _, files, decoded = gs3d
    key = f"ours_l{level}_sh{degree}"
    ours, fmt = read_gaussians_raw(files[key])
    assert fmt == "ksplat"
    assert_same_decode(ours, decoded(key), key)


@needs_gs3d
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("level", LEVELS)
def test_gaussiansplats3d_ksplat_files_are_read_by_us(gs3d, level, degree):
    from scipy.spatial import cKDTree

    sources, files, decoded = gs3d
    key = f"gs3d_l{level}_sh{degree}"
    ours, fmt = read_gaussians_raw(files[key])
    assert fmt == "ksplat"
    assert_same_decode(ours, decoded(key), key)
    # the Gaussians written, matched by position (the writer regroups them into buckets), within a step of each grid
    original = sources[degree]
    distance, match = cKDTree(original.means).query(ours.means)
    assert len(np.unique(match)) == len(original) == len(ours)
    src = original.subset(match)
    position_tol = POSITION_STEP[level] + FLOAT32_RELATIVE * float(np.abs(original.means).max())
    assert np.abs(ours.means - src.means).max() <= position_tol
    assert np.abs(ours.opacities() - src.opacities()).max() <= BYTE_STEP + 1e-6
    assert np.abs(ours.dc_colors() - np.clip(src.dc_colors(), 0, 1)).max() <= BYTE_STEP + 1e-6
    scales, expected = np.exp(ours.log_scales.astype(np.float64)), np.exp(src.log_scales.astype(np.float64))
    relative = FLOAT32_RELATIVE if level == 0 else HALF16_RELATIVE_STEP
    assert (np.abs(scales - expected) <= relative * expected + (HALF16_SUBNORMAL if level else 0) + 1e-12).all()
    assert _sign_free_quat_error(ours.quats, src.quats).max() <= relative + FLOAT32_RELATIVE
    if degree:
        sh_min, sh_max = struct.unpack_from("<ff", files[key].read_bytes(), SH_RANGE_OFFSET)
        rest = {0: FLOAT32_RELATIVE, 1: HALF16_RELATIVE_STEP * np.abs(src.sh[:, 1:]).max(),
                2: (sh_max - sh_min) / 255}[level]
        assert np.abs(ours.sh[:, 1:] - src.sh[:, 1:]).max() <= rest + FLOAT_SLACK


@needs_gs3d
def test_our_splat_files_decode_like_gaussiansplats3d(gs3d):
    """Our .splat writer read by GaussianSplats3D's SplatParser: the quaternion bytes in the order w, x, y, z (w at
    byte 28) and positions unconverted. Its parser decodes a component as ``(b - 128) / 128`` then normalizes, ours
    as ``(b - 127.5) / 127.5``: the rotations agree within a byte step; every other value is the same bytes. Its
    loader reorders the splats: matched by (exactly equal) position."""
    from scipy.spatial import cKDTree

    sources, files, decoded = gs3d
    ours, fmt = read_gaussians_raw(files["ours_splat"])
    assert fmt == "splat"
    theirs = decoded("ours_splat")
    distance, match = cKDTree(theirs.means).query(ours.means)
    assert distance.max() == 0 and len(np.unique(match)) == len(ours) == len(theirs)
    theirs = theirs.subset(match)
    np.testing.assert_allclose(ours.log_scales, theirs.log_scales, atol=DECODE_ATOL, rtol=1e-6)
    np.testing.assert_allclose(ours.sh, theirs.sh, atol=DECODE_ATOL, rtol=1e-6)
    np.testing.assert_allclose(ours.opacities(), theirs.opacities(), atol=DECODE_ATOL)
    assert _sign_free_quat_error(ours.quats, theirs.quats).max() <= 2 * SPLAT_QUAT_BYTE_STEP
    assert _sign_free_quat_error(theirs.quats, sources[0].quats).max() <= 2 * SPLAT_QUAT_BYTE_STEP
