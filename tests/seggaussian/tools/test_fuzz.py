"""Seeded fuzzing of the splat readers (seggaussian.tools.fuzz.engine) and the PLY strictness it enforces."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from seggaussian.tools.fuzz import engine as fuzz

from seggaussian.tools.fuzz import ply as fuzz_ply
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.header import PlyFormatError
from seggaussian.io.ply.reader import read_gaussians_ply, read_vertex_table
from seggaussian.io.ply.reference import read_vertex_table_plyfile
from seggaussian.io.ply.writer import write_gaussians_ply
from shared_data import REALDATA

REAL_PLYS = sorted(REALDATA.glob("*.ply")) if REALDATA.is_dir() else []
needs_realdata = pytest.mark.skipif(len(REAL_PLYS) < 2, reason=f"real 3DGS PLYs not found in {REALDATA}")
#: Mutants per CI run: the whole campaign (reading one mutant takes well under a millisecond).
CI_MUTANTS = 1600


@pytest.fixture(scope="module")
def target():
    return fuzz_ply.ply_target(REAL_PLYS, seed=0)


@needs_realdata
def test_ply_fuzz_campaign_no_crash_no_hang(target, tmp_path):
    start = time.perf_counter()
    report = fuzz.run_fuzz(target, CI_MUTANTS, seed=18, workdir=tmp_path)
    counts = report.counts
    assert sum(counts.values()) == CI_MUTANTS
    assert report.failures() == [], [f"{o.name}: {o.verdict}: {o.detail}" for o in report.failures()[:10]]
    # both outcomes occur, and every mutator was used
    assert counts["accepted"] > 50 and counts["clean_error"] > 500, counts
    assert set(report.by_mutator()) == {name for name, _ in target.mutators}
    assert {name.split("/")[0] for name in (o.name for o in report.outcomes)} == {n for n, _ in target.seeds}
    assert not list(tmp_path.iterdir())
    assert time.perf_counter() - start < 60


@needs_realdata
def test_accepted_mutants_read_the_same_through_plyfile(target, tmp_path):
    """Every binary mutant we accept is read identically by the independent plyfile reference."""
    compared = 0
    for i, mutant in enumerate(fuzz.make_mutants(target, 400, seed=5)):
        path = tmp_path / f"m{i}.ply"
        path.write_bytes(mutant.data)
        try:
            ours = read_vertex_table(path)
            read_gaussians_ply(path)
        except PlyFormatError:
            continue
        try:
            reference = read_vertex_table_plyfile(path)
        except UnicodeDecodeError:
            # plyfile mis-reads CRLF headers followed by a list element; we accept CRLF headers
            assert b"\r\n" in mutant.data[:200], mutant.name
            continue
        assert ours.dtype.names == reference.dtype.names, mutant.name
        assert ours.tobytes() == reference.tobytes(), mutant.name
        compared += 1
    assert compared > 20


def test_mutants_are_deterministic(target):
    a = fuzz.make_mutants(target, 60, seed=3)
    b = fuzz.make_mutants(target, 60, seed=3)
    c = fuzz.make_mutants(target, 60, seed=4)
    assert [m.data for m in a] == [m.data for m in b]
    assert [m.data for m in a] != [m.data for m in c]


def _tiny_target(read) -> fuzz.FuzzTarget:
    return fuzz.FuzzTarget("probe", read, [("seed", b"ply\nformat ascii 1.0\nend_header\n")],
                           fuzz.BYTE_MUTATORS, (ValueError,), ".bin")


def _gaussians(n=2) -> Gaussians:
    z = np.zeros((n, 3), np.float32)
    return Gaussians(z, np.tile(np.float32([1, 0, 0, 0]), (n, 1)), z, np.zeros(n, np.float32), z[:, None, :])


@pytest.mark.parametrize("read, verdict", [
    (lambda p: {}["missing"], "crash"),                                   # KeyError
    (lambda p: (_ for _ in ()).throw(ValueError("no path named")), "crash"),
    (lambda p: np.array(["x"]).astype(float), "crash"),                  # ValueError inside numpy
    (lambda p: (time.sleep(5), _gaussians())[1], "hang"),
    (lambda p: Gaussians(np.full((1, 3), np.nan, np.float32), np.float32([[1, 0, 0, 0]]), np.zeros((1, 3), np.float32),
                         np.zeros(1, np.float32), np.zeros((1, 1, 3), np.float32)), "nonfinite"),
    (lambda p: _gaussians(), "accepted"),
])
def test_classifier_sees_each_failure_kind(tmp_path, read, verdict):
    report = fuzz.run_fuzz(_tiny_target(read), 3, seed=0, workdir=tmp_path, timeout_s=0.2)
    assert {o.verdict for o in report.outcomes} == {verdict}


def test_classifier_clean_error_names_the_file(tmp_path):
    def read(path):
        raise ValueError(f"{path}: refused")

    # raised from a test module, not our package: the classifier calls that a crash ...
    assert fuzz.run_fuzz(_tiny_target(read), 2, 0, tmp_path).counts["crash"] == 2
    # ... while our reader's refusals are clean
    target = fuzz.FuzzTarget("ply", lambda p: read_gaussians_ply(p)[0], [("empty", b"")], fuzz.BYTE_MUTATORS[:1],
                             (PlyFormatError,))
    assert fuzz.run_fuzz(target, 2, 0, tmp_path).counts["clean_error"] == 2


# --- the findings of the fault campaign, one by one -----------------------------------------------
def _written(tmp_path, n=10, degree=3, **options) -> Path:
    rng = np.random.default_rng(1)
    k = (degree + 1) ** 2
    g = Gaussians(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                  rng.normal(size=(n, k, 3)).astype(np.float32))
    path = tmp_path / "g.ply"
    write_gaussians_ply(path, g, **options)
    return path


def _edit(path: Path, old: bytes, new: bytes, body=None) -> Path:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].replace(old, new, 1)
    out = path.with_name("edited.ply")
    out.write_bytes(head + (data[end:] if body is None else body))
    return out


def _refused(path: Path, *needles: str) -> str:
    with pytest.raises(PlyFormatError) as info:
        read_gaussians_ply(path)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle in message, message
    return message


def test_zero_padded_sh_name_is_an_extra_not_coefficient(tmp_path):
    path = _edit(_written(tmp_path), b"property float f_rest_5\n", b"property float f_rest_05\n")
    _refused(path, "f_rest_* properties are not numbered")


def test_ascii_body_under_binary_header_is_refused(tmp_path):
    binary = _written(tmp_path, n=200, degree=0)
    ascii_body = _written(tmp_path / "ascii", n=200, degree=0, binary=False).read_bytes()
    body = ascii_body[ascii_body.index(b"end_header\n") + 11:]
    _refused(_edit(binary, b"", b"", body=body), "body size mismatch", "bytes follow the header")


@pytest.mark.parametrize("count, needle", [(9, "more than declared"), (0, "more than declared"),
                                           (11, "truncated body")])
def test_vertex_count_must_match_the_body(tmp_path, count, needle):
    path = _edit(_written(tmp_path), b"element vertex 10\n", f"element vertex {count}\n".encode())
    _refused(path, needle, f"{count} vertices")


@pytest.mark.parametrize("tail", [b"\x00", b"\n", b"garbage" * 3])
def test_trailing_bytes_are_refused(tmp_path, tail):
    path = _written(tmp_path)
    path.write_bytes(path.read_bytes() + tail)
    _refused(path, "body size mismatch", f"{len(tail)} bytes more")


def test_trailing_lines_of_an_ascii_body_are_refused(tmp_path):
    path = _written(tmp_path, binary=False)
    path.write_bytes(path.read_bytes() + b"1 2 3\n")
    _refused(path, "body size mismatch", "11 non-empty lines")
    path.write_bytes(path.read_bytes()[:-6] + b"\n\n")  # blank lines are not data
    read_gaussians_ply(path)


@pytest.mark.parametrize("binary", [True, False])
def test_declared_element_without_data_is_refused_as_plyfile_does(tmp_path, binary):
    path = _edit(_written(tmp_path, binary=binary), b"end_header",
                 b"element face 10\nproperty list uchar int vertex_indices\nend_header")
    _refused(path, "face")
    with pytest.raises(Exception):
        read_vertex_table_plyfile(path)
    # with its data the element is fine (and skipped)
    data = path.read_bytes()
    record = (b"\x03" + np.arange(3, dtype="<i4").tobytes()) if binary else b"3 0 1 2\n"
    path.write_bytes(data + record * 10)
    read_gaussians_ply(path)
