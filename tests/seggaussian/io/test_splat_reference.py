"""Our splat readers and writers against an independent reference: @playcanvas/splat-transform (npm).

``make setup`` installs the converter into ``.node/`` where node and npm exist; without it these tests
skip with the reason. Every conversion runs the converter's CLI; they run a few at a time in parallel
(node start-up dominates) from one fixture shared by the whole test run.

Directions checked:

* reference writes (compressed PLY, SPZ v3, SPZ v4) from a PLY the test writes -> our reader equals the
  reference's own decode of the same file (both decode the same bytes: float32 rounding only) and the
  test's Gaussians within the format's quantisation step;
* our writers (compressed PLY, .splat, SPZ v2/v3/v4, .ksplat at compression levels 0/1/2 and SH degrees
  0-3) -> the reference reads our file, and its decode equals ours (the reference cannot write .ksplat,
  so this is the only direction for it);
* real PLYs from the open web (../shared/realdata, or $SEGGAUSSIAN_SHARED/realdata) converted by the reference to every format:
  counts and bounds of our decode agree with the reference's;
* files written by other programs (web_splats/splat_transform_fixtures: the reference repository's own
  fixtures: SPZ v3/v4 from Niantic's library via @adobe/spz, a hand-assembled level-0 .ksplat with a bucket,
  legacy SPZ and .splat files; see its SOURCES.md): our decode equals the reference's;
* splat files from the open web in other formats (../shared/realdata/web_splats, see its SOURCES.md: SuperSplat
  compressed PLYs and an SPZ v4 capture from playcanvas/engine, a tiny SPZ v4 from loaders.gl): detected by
  content, counts, bounds and every value equal to the reference's decode, validation passes; the SPZ and the
  compressed PLY of the same capture import to the same Gaussians.

Frames: the reference reads and writes SPZ without any frame conversion (its writer passes ``from: UNSPECIFIED``
to Niantic's library), where the format's author stores RUB and our reader and writer convert to and from the
toolkit's RDF (seggaussian/io/spz.py). So for SPZ the reference's values are ours under ``P = diag(1, -1, -1)``:
``reference_decode`` applies P to its decode of an SPZ file, and the SPZ files the reference writes from an RDF PLY
hold the PLY's values unconverted, so we read them turned by P. test_spz_niantic.py checks SPZ against Niantic's
own library.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import detect_format, read_gaussians, read_gaussians_raw, write_gaussians
from seggaussian.io.compressed_ply import morton_order
from seggaussian.io.ksplat import BLOCK_SIZE, DEFAULT_RANGE, bucket_layout, write_ksplat
from seggaussian.io.ply.reader import read_vertex_table, vertex_table_to_gaussians
from seggaussian.io.ply.writer import write_gaussians_ply
from shared_data import REALDATA, WEB_SPLATS

ROOT = Path(__file__).resolve().parents[3]
CLI = ROOT / ".node" / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"
REALDATA_DIRS = (REALDATA,)
REAL_FILES = ("loadersgl_train-1000.ply", "v3dg_donut_fused_sh0.ply")
#: Splat files from the open web (not in the repository: fetched data stays in shared/, see tests/shared_data.py).
WEB_SPLAT_DIRS = (WEB_SPLATS,)
#: name -> (format detected by content, Gaussian count from the file's header; see web_splats/SOURCES.md)
WEB_SPLATS = {"guitar.compressed.ply": ("compressed_ply", 90_854), "biker.compressed.ply": ("compressed_ply", 152_746),
              "biker.spz": ("spz", 152_746), "two-splats.spz": ("spz", 2)}
#: Fetched from other repositories, so kept beside the web splats in shared/, not in this repository.
FIXTURE_SUBDIR = "splat_transform_fixtures"
FIXTURE_FILES = ("minimal-raw.spz", "minimal-v2.spz", "minimal-v3.spz", "minimal-v4.spz", "minimal.ksplat",
                 "minimal.splat")
#: Float32 rounding between two decoders of the same bytes (the reference computes in float64 JS numbers).
DECODE_ATOL = 2e-6
#: The same for quaternions whose largest component is recomputed as sqrt(1 - sum of squares).
QUAT_DECODE_ATOL = 3e-5
#: .ksplat levels 1-2: position step inside a bucket (block / 2 / range), float16 relative step.
KSPLAT_POSITION_STEP = BLOCK_SIZE / 2 / DEFAULT_RANGE[1]
HALF_STEP = 2.0 ** -11
#: The change of basis P = diag(1, -1, -1) between SPZ's RUB and the toolkit's RDF, as Niantic's coordinateConverter
#: writes it (src/cc/splat-types.h, x = 1, y = z = -1): positions (x, -y, -z); flipQ = (y z, x z, x y) on the
#: quaternion's x, y, z (w unchanged); flipSh = (y, z, x, xy, yz, 1, xz, 1, y, xyz, y, z, x, z, x), the DC first here.
P_POSITION = np.array([1, -1, -1])
P_QUAT = np.array([1, 1, -1, -1])                      # w, x, y, z
P_SH = np.array([1, -1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1])

needs_reference = pytest.mark.skipif(
    shutil.which("node") is None or not CLI.is_file(),
    reason=f"@playcanvas/splat-transform not installed ({CLI} missing or no node); run `make setup` with node/npm",
)


def _realdata() -> Path | None:
    return next((d for d in REALDATA_DIRS if all((d / f).is_file() for f in REAL_FILES)), None)


def _web_splats() -> Path | None:
    return next((d for d in WEB_SPLAT_DIRS if any((d / f).is_file() for f in WEB_SPLATS)), None)


def _skip_without_web_data(what: str, origin: str) -> None:
    """Skip a test whose fetched files are absent, saying where they were looked for."""
    pytest.skip(f"{what} not found in {' or '.join(map(str, WEB_SPLAT_DIRS))} ({origin}; fetched data is kept in "
                "shared/realdata/web_splats with a SOURCES.md, not in this repository)")


def _fixtures() -> Path | None:
    return next((d / FIXTURE_SUBDIR for d in WEB_SPLAT_DIRS
                 if all((d / FIXTURE_SUBDIR / f).is_file() for f in FIXTURE_FILES)), None)


def convert_all(jobs: list[tuple[Path, Path, tuple[str, ...]]]) -> None:
    """Run ``splat-transform [options] src dst`` for every job, a few in parallel; fail with its stderr."""
    def run(job):
        src, dst, options = job
        result = subprocess.run(["node", str(CLI), "-q", "-w", *options, str(src), str(dst)],
                                capture_output=True, text=True, timeout=300)
        return job, result

    with ThreadPoolExecutor(max_workers=4) as pool:
        for (src, dst, _), result in pool.map(run, jobs):
            assert result.returncode == 0 and dst.is_file(), f"splat-transform {src} -> {dst}: {result.stderr[-2000:]}"


def apply_p(g: Gaussians) -> Gaussians:
    """``g`` under the change of basis P (RUB <-> RDF; its own inverse), Niantic's signs (``P_*`` above)."""
    return Gaussians.from_arrays(g.means * P_POSITION, g.quats * P_QUAT, g.log_scales, g.opacity_logits,
                                 g.sh * P_SH[: g.sh.shape[1], None])


def reference_decode(path: Path) -> Gaussians:
    """The reference's decode of ``path`` (converted by it to a plain PLY beforehand), in our frame: for an SPZ
    file P is applied, since the reference reads SPZ raw (RUB values as they are) and we convert RUB -> RDF."""
    table = read_vertex_table(path.with_name(path.name + ".ref.ply"))
    decoded = vertex_table_to_gaussians(table, source=path)
    return apply_p(decoded) if detect_format(path) == "spz" else decoded


def make_gaussians(degree: int, seed: int, n: int = 700) -> Gaussians:
    """Gaussians with extreme scales and opacities and non-unit quaternions (inside each format's range)."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    log_scales = rng.uniform(-9.5, 5.5, (n, 3))                  # SPZ's 8-bit log range is [-10, 5.9]
    log_scales[:8] = [[-9.9, -9.9, -9.9], [5.8, 5.8, 5.8], [-9.9, 0, 5.8], [0, 0, 0], [-5, -5, -5],
                      [1, 2, 3], [-9, 5, 0], [5, -9, 0]]
    opacity_logits = rng.normal(0, 4, n)
    opacity_logits[:6] = [-12, 12, -30, 30, 0, 1e-3]              # saturated and extreme
    quats = rng.normal(size=(n, 4)) * rng.uniform(0.05, 20, (n, 1))  # non-unit norms
    quats[:4] = [[1, 0, 0, 0], [0, 0, 0, 3], [-2, 0, 0, 0], [0.5, -0.5, 0.5, -0.5]]
    dc = rng.uniform(-0.5 / SH_C0 * 0.98, 0.5 / SH_C0 * 0.98, (n, 3))    # colours inside [0, 1]
    sh = np.concatenate([dc[:, None, :], rng.uniform(-0.95, 0.95, (n, k - 1, 3))], axis=1)
    means = rng.uniform(-40, 40, (n, 3))
    means[:2] = [[0, 0, 0], [1e-3, -1e-3, 2047.0]]
    return Gaussians.from_arrays(means, quats, log_scales, opacity_logits, sh)


def _unit(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _sign_free_quat_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Largest component difference of two unit quaternions up to sign, per row."""
    a, b = _unit(a.astype(np.float64)), _unit(b.astype(np.float64))
    return np.minimum(np.abs(a - b).max(axis=1), np.abs(a + b).max(axis=1))


@pytest.fixture(scope="session")
def reference_files(tmp_path_factory):
    """Every file of the comparison, converted once: ``{name: path}`` plus the source Gaussians."""
    if shutil.which("node") is None or not CLI.is_file():
        pytest.skip(f"@playcanvas/splat-transform not installed ({CLI}); run `make setup` with node/npm")
    d = tmp_path_factory.mktemp("splat_reference")
    sources: dict[str, Gaussians] = {}
    jobs = []
    files: dict[str, Path] = {}
    for degree in range(4):
        g = make_gaussians(degree, seed=degree)
        sources[f"sh{degree}"] = g
        src = d / f"sh{degree}.ply"
        write_gaussians_ply(src, g)
        # reference writers: compressed PLY, SPZ v3 (gzip) and v4 (zstd)
        for tag, name, options in (("ref_cply", f"sh{degree}.compressed.ply", ()),
                                   ("ref_spz3", f"sh{degree}_v3.spz", ("--spz-version", "3")),
                                   ("ref_spz4", f"sh{degree}_v4.spz", ("--spz-version", "4"))):
            files[f"{tag}_sh{degree}"] = d / name
            jobs.append((src, d / name, options))
        # our writers, read back by the reference below
        for tag, name, kwargs in (("our_cply", f"our_sh{degree}.compressed.ply", {}),
                                  ("our_splat", f"our_sh{degree}.splat", {}),
                                  ("our_spz2", f"our_sh{degree}_v2.spz", {"spz_version": 2}),
                                  ("our_spz3", f"our_sh{degree}_v3.spz", {"spz_version": 3}),
                                  ("our_spz4", f"our_sh{degree}_v4.spz", {"spz_version": 4})):
            if tag == "our_splat" and degree:
                continue
            write_gaussians(d / name, g, **kwargs)
            files[f"{tag}_sh{degree}"] = d / name
        for level in (0, 1, 2):       # degree 3 too: GaussianSplats3D stops at 2, the reference reads 3
            write_ksplat(d / f"our_sh{degree}_l{level}.ksplat", g, compression_level=level, max_sh_degree=3)
            files[f"our_ksplat{level}_sh{degree}"] = d / f"our_sh{degree}_l{level}.ksplat"
    real = _realdata()
    if real is not None:
        for stem in (Path(f).stem for f in REAL_FILES):
            for tag, name, options in (("ref_cply", f"{stem}.compressed.ply", ()),
                                       ("ref_spz3", f"{stem}_v3.spz", ("--spz-version", "3")),
                                       ("ref_spz4", f"{stem}_v4.spz", ("--spz-version", "4"))):
                files[f"real_{tag}_{stem}"] = d / name
                jobs.append((real / f"{stem}.ply", d / name, options))
            g, _, _ = read_gaussians(real / f"{stem}.ply")
            files[f"real_our_splat_{stem}"] = d / f"{stem}.splat"
            write_gaussians(d / f"{stem}.splat", g)
            files[f"real_our_ksplat_{stem}"] = d / f"{stem}.ksplat"
            write_gaussians(d / f"{stem}.ksplat", g)
            sources[f"real_{stem}"] = g
    fixtures = _fixtures()
    for name in FIXTURE_FILES if fixtures is not None else ():  # copied: the reference's decode goes beside each
        shutil.copyfile(fixtures / name, d / f"fixture_{name}")
        files[f"fixture_{name}"] = d / f"fixture_{name}"
    web = _web_splats()
    for name in WEB_SPLATS if web is not None else ():
        if (web / name).is_file():
            shutil.copyfile(web / name, d / f"web_{name}")
            files[f"web_{name}"] = d / f"web_{name}"
    convert_all(jobs)
    # the reference decodes every non-PLY file back to a plain PLY
    convert_all([(path, path.with_name(path.name + ".ref.ply"), ()) for path in files.values()])
    return files, sources


def _compare_decodes(ours: Gaussians, ref: Gaussians, what: str) -> None:
    assert len(ours) == len(ref), what
    assert ours.sh_degree == ref.sh_degree, what
    # lerps between chunk bounds are float32 here: rounding scales with the magnitude of the bounds
    atol_means = max(DECODE_ATOL, 8 * float(np.finfo(np.float32).eps) * float(np.abs(ref.means).max(initial=0)))
    np.testing.assert_allclose(ours.means, ref.means, atol=atol_means, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.log_scales, ref.log_scales, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    np.testing.assert_allclose(ours.sh, ref.sh, atol=DECODE_ATOL, rtol=1e-6, err_msg=what)
    # w = sqrt(1 - |xyz|^2) (SPZ v2, smallest-three) amplifies float32 rounding near w = 0
    assert _sign_free_quat_error(ours.quats, ref.quats).max() < QUAT_DECODE_ATOL, what
    # the reference returns +-inf logits for compressed-PLY opacity bytes 0/255; we clamp (UNIT_OPACITY_EPS)
    np.testing.assert_allclose(ours.opacities(), ref.opacities(), atol=2e-6, err_msg=what)


@needs_reference
@pytest.mark.parametrize("degree", range(4))
@pytest.mark.parametrize("tag", ["ref_cply", "ref_spz3", "ref_spz4"])
def test_reference_written_files_decode_like_the_reference(reference_files, tag, degree):
    files, sources = reference_files
    path = files[f"{tag}_sh{degree}"]
    expected = {"ref_cply": "compressed_ply", "ref_spz3": "spz", "ref_spz4": "spz"}[tag]
    assert detect_format(path) == expected
    renamed = path.with_name(path.name + ".bin")           # detection is by content, not by name
    shutil.copyfile(path, renamed)
    ours, fmt = read_gaussians_raw(renamed)
    assert fmt == expected
    _compare_decodes(ours, reference_decode(path), f"{tag} sh{degree}")
    # ... and within the format's quantisation step of what the test wrote (compressed PLY reorders: sort); the
    # reference stores the PLY's RDF values in SPZ unconverted, so the frame rule reads them turned by P
    original = sources[f"sh{degree}"] if tag == "ref_cply" else apply_p(sources[f"sh{degree}"])
    if tag == "ref_cply":
        order_ours = np.lexsort(ours.means.T)
        match = [int(np.argmin(np.abs(original.means - m).sum(1))) for m in ours.means[order_ours][:50]]
        src = original.subset(np.array(match))
        got = ours.subset(order_ours[:50])
        extent = np.ptp(original.means, axis=0)
        assert (np.abs(got.means - src.means) <= extent / 1023 + 1e-4).all()       # within one chunk step
        assert (np.abs(got.sh[:, 1:] - src.sh[:, 1:]) <= 8 / 256 + 1e-6).all()       # SH byte step
        assert (_sign_free_quat_error(got.quats, src.quats) <= np.sqrt(2) / 1023 + 1e-3).all()
    else:
        assert (np.abs(ours.means - original.means) <= 0.5 / 4096 + 1e-6).all()    # 12 fraction bits
        assert (np.abs(ours.log_scales - np.clip(original.log_scales, -10, 5.9375)) <= 0.5 / 16 + 1e-5).all()
        assert (np.abs(ours.opacities() - original.opacities()) <= 0.5 / 255 + 1e-6).all()
        assert (np.abs(ours.sh[:, 0] - original.sh[:, 0]) <= 0.5 / (255 * 0.15) + 1e-5).all()
        # SH: the reference library quantises band 1 to 5 bits (step 8/128) and bands 2-3 to 4 bits (16/128),
        # on top of the 1/128 byte step
        err = np.abs(ours.sh[:, 1:] - original.sh[:, 1:])
        assert (err[:, :3] <= 4 / 128 + 1 / 128 + 1e-5).all() and (err <= 8 / 128 + 1 / 128 + 1e-5).all()
        assert (_sign_free_quat_error(ours.quats, original.quats) <= 1 / (511 * np.sqrt(2)) * 2 + 1e-5).all()


@needs_reference
@pytest.mark.parametrize("tag, degree", [(t, d) for t in ("our_cply", "our_spz2", "our_spz3", "our_spz4")
                                          for d in range(4)] + [("our_splat", 0)])   # .splat: DC colour only
def test_our_files_are_read_by_the_reference(reference_files, tag, degree):
    files, sources = reference_files
    path = files[f"{tag}_sh{degree}"]
    ours, _ = read_gaussians_raw(path)
    ref = reference_decode(path)
    _compare_decodes(ours, ref, f"{tag} sh{degree}")
    original = sources[f"sh{degree}"]
    if tag == "our_cply":                                   # stored in Morton order, as the reference does
        original = original.subset(morton_order(original.means))
    # values within the quantisation steps of the format
    tol_means = {"our_cply": np.ptp(original.means, axis=0) / 1023 + 1e-4, "our_splat": 1e-6}.get(tag, 0.5 / 4096 + 1e-6)
    assert (np.abs(ours.means - original.means) <= tol_means).all()
    tol_opacity = 0.5 / 255 + 1e-6 if tag != "our_splat" else 0.5 / 255 + 1e-6
    assert (np.abs(ours.opacities() - original.opacities()) <= tol_opacity).all()
    if tag == "our_spz2":
        # v2 stores x, y, z (w >= 0) in 8 bits each and derives w = sqrt(1 - |xyz|^2): x, y, z within the
        # byte step; w (ill-conditioned near 0, the reason for v3's smallest-three) is not checked here
        unit = _unit(original.quats.astype(np.float64))
        assert (np.abs(ours.quats[:, 1:] - unit[:, 1:]) <= 1 / 127.5 + 1e-5).all()
    else:
        assert (_sign_free_quat_error(ours.quats, original.quats) <= 2 / 127.5).all()


@needs_reference
def test_real_files_counts_and_bounds_agree_with_the_reference(reference_files):
    files, sources = reference_files
    real = [key for key in files if key.startswith("real_")]
    if not real:
        pytest.skip(f"real PLYs not found in {REALDATA}")
    for key in real:
        path = files[key]
        loaded = read_gaussians(path, on_invalid="report")
        ref = reference_decode(path)
        assert len(loaded.gaussians) == len(ref) > 0, key
        np.testing.assert_allclose(loaded.gaussians.means.min(0), ref.means.min(0), atol=1e-5, err_msg=key)
        np.testing.assert_allclose(loaded.gaussians.means.max(0), ref.means.max(0), atol=1e-5, err_msg=key)
        stem = key.split("_", 3)[-1]
        original = sources[f"real_{stem}"]
        if key.startswith("real_ref_spz"):          # the reference writes SPZ unconverted: read turned by P
            original = apply_p(original)
        assert len(original) == len(ref)
        step = {"our_splat": 1e-6, "our_ksplat": KSPLAT_POSITION_STEP / 2 + 1e-6}.get(
            key.split("_")[1] + "_" + key.split("_")[2], np.ptp(original.means, axis=0).max() / 1023 + 1e-3)
        np.testing.assert_allclose(loaded.gaussians.means.min(0), original.means.min(0), atol=step, err_msg=key)
        np.testing.assert_allclose(loaded.gaussians.means.max(0), original.means.max(0), atol=step, err_msg=key)


@needs_reference
@pytest.mark.parametrize("degree", range(4))
@pytest.mark.parametrize("level", [0, 1, 2])
def test_our_ksplat_files_are_read_by_the_reference(reference_files, level, degree):
    """The reference reads .ksplat but cannot write it: our writer's files, every level and SH degree."""
    files, sources = reference_files
    path = files[f"our_ksplat{level}_sh{degree}"]
    renamed = path.with_name(path.name + ".bin")           # detection is by content, not by name
    shutil.copyfile(path, renamed)
    ours, fmt = read_gaussians_raw(renamed)
    assert fmt == "ksplat"
    ref = reference_decode(path)
    _compare_decodes(ours, ref, f"ksplat level {level} sh{degree}")
    # within the quantisation step of what the test wrote (levels 1-2 store bucket by bucket)
    original = sources[f"sh{degree}"]
    original = original.subset(bucket_layout(original.means).order) if level else original
    assert ours.sh_degree == original.sh_degree
    position_step, float_step = (0.0, 1e-6) if level == 0 else (KSPLAT_POSITION_STEP / 2, HALF_STEP)
    assert (np.abs(ours.means - original.means) <= position_step + 1e-6 * np.abs(original.means) + 1e-6).all()
    # float16 scales: relative step, plus the subnormal step 2^-24 for the smallest (log -9.9: 5e-5 m)
    scales, expected = np.exp(ours.log_scales.astype(np.float64)), np.exp(original.log_scales.astype(np.float64))
    assert (np.abs(scales - expected) <= float_step * expected + (2.0 ** -24 if level else 0) + 1e-12).all()
    assert (np.abs(ours.opacities() - original.opacities()) <= 0.5 / 255 + 1e-6).all()
    assert (np.abs(ours.dc_colors() - original.dc_colors()).max() <= 0.5 / 255 + 1e-6)
    rest_step = {0: 1e-6, 1: HALF_STEP, 2: np.abs(original.sh[:, 1:]).max(initial=0) / 255}[level]
    assert (np.abs(ours.sh[:, 1:] - original.sh[:, 1:]) <= rest_step + 1e-6).all()
    assert (_sign_free_quat_error(ours.quats, original.quats) <= float_step + 1e-6).all()


def _decode_by_content_like_the_reference(path: Path, expected_format: str, name: str):
    """(ours, the reference's) decodes of a file written by another program: ours reads a copy whose name says
    nothing (detection is by content), must name ``expected_format``, and must equal the reference's decode."""
    renamed = path.with_name(path.name + ".bin")
    shutil.copyfile(path, renamed)
    ours, fmt = read_gaussians_raw(renamed)
    assert fmt == expected_format
    ref = reference_decode(path)
    _compare_decodes(ours, ref, name)
    return ours, ref


@needs_reference
@pytest.mark.parametrize("name", FIXTURE_FILES)
def test_files_written_by_other_programs_decode_like_the_reference(reference_files, name):
    files, _ = reference_files
    if f"fixture_{name}" not in files:
        _skip_without_web_data(f"{FIXTURE_SUBDIR}/{name}", "the reference repository's fixtures")
    path = files[f"fixture_{name}"]
    expected = {"spz": "spz", "ksplat": "ksplat", "splat": "splat"}[name.rsplit(".", 1)[1]]
    ours, ref = _decode_by_content_like_the_reference(path, expected, name)
    np.testing.assert_array_equal(ours.means.min(0), ref.means.min(0))
    np.testing.assert_array_equal(ours.means.max(0), ref.means.max(0))
    loaded = read_gaussians(path)                          # and it passes validation
    assert loaded.report.ok and len(loaded.gaussians) == 4
    # the generator's values (test/fixtures/create-fixtures.mjs): a 2 x 2 grid (x, z in {-1, 0}) with 1 m spacing,
    # scale 0.1, opacity 230/255; SPZ stores the scale as a log in 1/16 steps. v3/v4 were written by Niantic's
    # library from RDF (``from: RDF``, stored RUB): read back as written. raw/v2 were assembled byte by byte with
    # the RDF values in RUB's place (no conversion), so the frame rule reads them turned by P (z negated; y is 0)
    assert sorted(map(tuple, np.round(ours.means[:, [0, 2]]).tolist())) == (
        [(-1, 0), (-1, 1), (0, 0), (0, 1)] if name in ("minimal-raw.spz", "minimal-v2.spz")
        else [(-1, -1), (-1, 0), (0, -1), (0, 0)])
    np.testing.assert_allclose(np.exp(ours.log_scales), 0.1, rtol=0.02 if expected == "spz" else 1e-6)
    np.testing.assert_allclose(ours.opacities(), 230 / 255, atol=0.5 / 255)


@needs_reference
@pytest.mark.parametrize("degree", range(4))
def test_our_compressed_ply_has_the_reference_writers_order(reference_files, degree):
    """Both writers Morton-sort before chunking: the same Gaussians land in the same places and chunks."""
    files, sources = reference_files
    ours, _ = read_gaussians_raw(files[f"our_cply_sh{degree}"])
    theirs, _ = read_gaussians_raw(files[f"ref_cply_sh{degree}"])
    step = np.ptp(sources[f"sh{degree}"].means, axis=0) / 1023 + 1e-4      # one position step of the widest chunk
    assert (np.abs(ours.means - theirs.means) <= step).all()
    # same chunk membership: the same per-chunk lower position bounds (stored exactly as float32)
    edges = np.arange(0, len(ours), 256)
    np.testing.assert_allclose(np.minimum.reduceat(ours.means, edges), np.minimum.reduceat(theirs.means, edges),
                               atol=1e-4)


@needs_reference
@pytest.mark.parametrize("name", WEB_SPLATS)
def test_web_splats_decode_like_the_reference(reference_files, name):
    """Captures from public repositories, written by SuperSplat and PlayCanvas's SPZ conversion, not by us."""
    files, _ = reference_files
    if f"web_{name}" not in files:
        _skip_without_web_data(name, "captures from playcanvas/engine and visgl/loaders.gl")
    path = files[f"web_{name}"]
    expected_format, expected_count = WEB_SPLATS[name]
    assert detect_format(path) == expected_format
    ours, ref = _decode_by_content_like_the_reference(path, expected_format, name)
    # both decode the same bytes: counts equal, every value (and so the bounds) within float32 rounding
    assert len(ours) == len(ref) == expected_count
    atol = 8 * float(np.finfo(np.float32).eps) * float(np.abs(ref.means).max())
    np.testing.assert_allclose(ours.means.min(0), ref.means.min(0), atol=atol, rtol=0, err_msg=name)
    np.testing.assert_allclose(ours.means.max(0), ref.means.max(0), atol=atol, rtol=0, err_msg=name)
    loaded = read_gaussians(path, on_invalid="report")     # real files pass validation untouched
    assert loaded.report.ok and loaded.report.num_dropped == 0 and len(loaded.gaussians) == expected_count


#: Compressed PLY position bits per axis (x, y, z: 11/10/11) and the SPZ encodings' steps (seggaussian/io/spz.py):
#: log scale 1/16, DC colour 1 / (255 * 0.15) in f_dc units, quaternion components 1 / (511 sqrt 2) (v3+).
CPLY_POSITION_BITS = np.array([11, 10, 11])
SPZ_LOG_SCALE_STEP = 1 / 16
SPZ_DC_STEP = 1 / (255 * 0.15)
SPZ_QUAT_STEP = 1 / (511 * np.sqrt(2))
CPLY_QUAT_STEP = np.sqrt(2) / 1023
#: SPZ's 8-bit log scale covers [-10, 15.9375] (bytes 0..255); the compressed PLY holds smaller log scales.
SPZ_LOG_SCALE_RANGE = (-10.0, 255 / 16 - 10)
#: Float32 rounding of the compressed PLY's lerps, relative to the largest coordinate (as in _compare_decodes).
LERP_RELATIVE_ATOL = 8 * float(np.finfo(np.float32).eps)
#: Matches by nearest neighbour are used for the attributes when no second SPZ Gaussian lies within the position
#: bound (else the nearest may be a twin at the same place); at least this share of the capture must qualify.
MIN_UNAMBIGUOUS_SHARE = 0.95


def test_web_biker_spz_and_compressed_ply_hold_the_same_capture():
    """biker.spz is PlayCanvas's SPZ v4 conversion of the capture in biker.compressed.ply (SOURCES.md). Read by the
    frame rule (SPZ stores RUB, we hold RDF), both import to the same Gaussians: every compressed-PLY mean has an
    SPZ mean within the two formats' position rounding, and the matched Gaussians agree in opacity, scale, colour
    and rotation within the two formats' steps. Before the frame rule, y and z came out negated (the first
    Gaussian at (-0.104, 2.388, 0.361) from the SPZ, (-0.105, -2.388, -0.361) from the PLY)."""
    import plyfile
    from scipy.spatial import cKDTree

    web = _web_splats()
    if web is None or not (web / "biker.spz").is_file() or not (web / "biker.compressed.ply").is_file():
        _skip_without_web_data("biker.spz / biker.compressed.ply", "captures from playcanvas/engine")
    spz, _ = read_gaussians_raw(web / "biker.spz")
    cply, _ = read_gaussians_raw(web / "biker.compressed.ply")
    assert len(spz) == len(cply) == WEB_SPLATS["biker.spz"][1]
    # position bound per compressed-PLY Gaussian: half an SPZ step (fraction bits from the header; v4's is plain)
    # plus half a step of its chunk on each axis, plus float32 rounding of the lerp
    fractional_bits = (web / "biker.spz").read_bytes()[13]
    chunks = plyfile.PlyData.read(str(web / "biker.compressed.ply"))["chunk"].data
    chunk_of = np.arange(len(cply)) // 256
    extent = np.stack([chunks[f"max_{a}"] - chunks[f"min_{a}"] for a in "xyz"], axis=1)[chunk_of]
    per_axis = (0.5 / (1 << fractional_bits) + 0.5 * extent / (2.0 ** CPLY_POSITION_BITS - 1)
                + LERP_RELATIVE_ATOL * float(np.abs(cply.means).max()))
    bound = np.linalg.norm(per_axis, axis=1)
    distance, nearest = cKDTree(spz.means).query(cply.means, k=2)
    assert (distance[:, 0] <= bound).all(), (
        f"{int((distance[:, 0] > bound).sum())} compressed-PLY Gaussians have no SPZ Gaussian within the bound; "
        f"largest distance {distance[:, 0].max():.3g} m")
    assert np.median(distance[:, 0]) < np.median(bound)
    unambiguous = distance[:, 1] > bound
    assert unambiguous.mean() >= MIN_UNAMBIGUOUS_SHARE
    a, b = spz.subset(nearest[unambiguous, 0]), cply.subset(np.flatnonzero(unambiguous))
    chunk = chunk_of[unambiguous]
    # opacity: one byte in each format
    assert np.abs(a.opacities() - b.opacities()).max() <= 0.5 / 255 + 0.5 / 255 + 1e-6
    # log scale: SPZ's 1/16 step (clamped to its range), the chunk's 11/10/11-bit step of the log-scale bounds
    scale_extent = np.stack([chunks[f"max_scale_{a}"] - chunks[f"min_scale_{a}"] for a in "xyz"], axis=1)[chunk]
    scale_bound = 0.5 * SPZ_LOG_SCALE_STEP + 0.5 * scale_extent / (2.0 ** CPLY_POSITION_BITS - 1) + 1e-5
    assert (np.abs(a.log_scales - np.clip(b.log_scales, *SPZ_LOG_SCALE_RANGE)) <= scale_bound).all()
    # DC colour (f_dc): SPZ's byte step, the chunk colour bounds' 8-bit step (colour units / SH_C0)
    colour_extent = np.stack([chunks[f"max_{c}"] - chunks[f"min_{c}"] for c in "rgb"], axis=1)[chunk]
    dc_bound = 0.5 * SPZ_DC_STEP + 0.5 * colour_extent / 255 / SH_C0 + 1e-5
    assert (np.abs(a.sh[:, 0] - b.sh[:, 0]) <= dc_bound).all()
    # rotation (up to sign): a full step of each (the derived largest component carries the others' rounding)
    assert _sign_free_quat_error(a.quats, b.quats).max() <= SPZ_QUAT_STEP + CPLY_QUAT_STEP
