"""3DGS PLY reader/writer and import validation (seggaussian.io.ply, seggaussian.io.validate)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seggaussian.core.constants import LOG_SCALE_FLOAT32_MAX, OPACITY_LOGIT_SATURATION
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.ply.header import PlyFormatError, read_ply_header
from seggaussian.io.ply.reader import read_gaussians_ply, read_vertex_table
from seggaussian.io.ply.reference import read_vertex_table_plyfile
from seggaussian.io.ply.writer import write_atomic, write_gaussians_ply, write_vertex_table
from seggaussian.io.validate import validate_gaussians
from shared_data import REALDATA

TRAIN_1000 = REALDATA / "loadersgl_train-1000.ply"
DONUT = REALDATA / "v3dg_donut_fused_sh0.ply"
needs_realdata = pytest.mark.skipif(not TRAIN_1000.exists() or not DONUT.exists(),
                                    reason=f"real 3DGS files not found under {REALDATA}")


def random_gaussians(n, degree=1, seed=0, extras=None):
    rng = np.random.default_rng(seed)
    return Gaussians.from_arrays(
        rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)) - 3,
        rng.normal(size=n), rng.normal(size=(n, (degree + 1) ** 2, 3)), extras,
    )


def assert_same_gaussians(a: Gaussians, b: Gaussians):
    """Bitwise equality of every attribute and extra (NaN payloads included)."""
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape and x.dtype == y.dtype, name
        assert x.tobytes() == y.tobytes(), name
    assert list(a.extras) == list(b.extras)
    for name in a.extras:
        assert a.extras[name].dtype == b.extras[name].dtype, name
        assert a.extras[name].tobytes() == b.extras[name].tobytes(), name


def raw_records(path: Path, count: int):
    """Independent decoder: header names by hand, then struct.unpack of the first ``count`` records."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names = [line.split()[2] for line in data[:end].decode().splitlines() if line.startswith("property float ")]
    assert b"binary_little_endian" in data[:end]
    size = 4 * len(names)
    return [dict(zip(names, struct.unpack("<" + "f" * len(names), data[end + i * size: end + (i + 1) * size])))
            for i in range(count)]


# --------------------------------------------------------------------------------------------
# real files
# --------------------------------------------------------------------------------------------
@needs_realdata
@pytest.mark.parametrize("path, degree, normals", [(TRAIN_1000, 3, True), (DONUT, 0, False)])
def test_real_file_matches_raw_bytes(path, degree, normals):
    g, report = read_gaussians_ply(path)
    assert g.sh_degree == degree and report.ok and report.num_output == len(g)
    assert g.extras == {}  # zero normals are dropped, nothing else is extra
    k = (degree + 1) ** 2
    for i, rec in enumerate(raw_records(path, 20)):
        assert ("nx" in rec) == normals
        np.testing.assert_array_equal(g.means[i], np.float32([rec["x"], rec["y"], rec["z"]]))
        np.testing.assert_array_equal(g.quats[i], np.float32([rec[f"rot_{j}"] for j in range(4)]))
        np.testing.assert_array_equal(g.log_scales[i], np.float32([rec[f"scale_{j}"] for j in range(3)]))
        assert g.opacity_logits[i] == np.float32(rec["opacity"])
        for c in range(3):
            assert g.sh[i, 0, c] == np.float32(rec[f"f_dc_{c}"])
            for j in range(1, k):  # channel-major: all R coefficients, then G, then B
                assert g.sh[i, j, c] == np.float32(rec[f"f_rest_{c * (k - 1) + j - 1}"])


@needs_realdata
@pytest.mark.parametrize("path", [TRAIN_1000, DONUT])
def test_real_file_fast_reader_equals_plyfile_reference(path):
    fast, slow = read_vertex_table(path), read_vertex_table_plyfile(path)
    assert fast.dtype == slow.dtype
    assert fast.tobytes() == slow.tobytes()


@needs_realdata
def test_real_file_quaternions_not_unit_accepted_and_normalized_on_use():
    g, _ = read_gaussians_ply(TRAIN_1000)
    norms = np.linalg.norm(g.quats.astype(np.float64), axis=1)
    assert norms.min() < 0.9 and norms.max() > 1.1  # stored as on disk, not normalized
    np.testing.assert_allclose(np.linalg.norm(g.normalized_quats(), axis=1), 1.0, atol=1e-6)


@needs_realdata
@pytest.mark.parametrize("path, normals", [(TRAIN_1000, True), (DONUT, False)])
def test_real_file_rewritten_byte_identical(tmp_path, path, normals):
    g, _ = read_gaussians_ply(path)
    out = tmp_path / "out.ply"
    write_gaussians_ply(out, g, normals=normals)
    assert out.read_bytes() == path.read_bytes()


# --------------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------------
EXTRA_KINDS = {
    "semantic": lambda rng, n: rng.integers(0, 100, n).astype(np.int32),
    "instance": lambda rng, n: rng.integers(0, 70000, n).astype(np.int32),
    "flag": lambda rng, n: rng.integers(0, 255, n).astype(np.uint8),
    "transfer_distance": lambda rng, n: rng.random(n),  # float64 -> PLY double
    "feature": lambda rng, n: rng.normal(size=(n, 3)).astype(np.float32),  # [N, 3] -> feature_0..2
    "nx": None,  # marker: non-zero normals kept as extras
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n=st.integers(0, 12),
    degree=st.integers(0, 3),
    fmt=st.sampled_from(["<", ">", "ascii"]),
    normals=st.booleans(),
    extra_names=st.lists(st.sampled_from(sorted(EXTRA_KINDS)), unique=True, max_size=4),
    seed=st.integers(0, 2**31 - 1),
)
def test_round_trip_property(tmp_path_factory, n, degree, fmt, normals, extra_names, seed):
    rng = np.random.default_rng(seed)
    extras = {}
    for name in extra_names:
        if name == "nx":
            if n == 0:  # zero rows: normals count as "all zero" and are dropped on read (documented)
                continue
            for axis in ("nx", "ny", "nz"):
                extras[axis] = rng.normal(size=n).astype(np.float32) + 1.0
        else:
            extras[name] = EXTRA_KINDS[name](rng, n)
    g = random_gaussians(n, degree, seed, extras)
    # awkward but valid float32 values: subnormals, negative zero, extremes
    if n >= 2:
        g.sh[0, 0, 0] = -0.0
        g.sh[1, -1, 2] = np.float32(1e-45)
        g.means[1, 2] = np.float32(3.4e38)
    path = tmp_path_factory.mktemp("rt") / "g.ply"
    kwargs = dict(binary=fmt != "ascii", endian=fmt if fmt != "ascii" else "<", normals=normals)
    write_gaussians_ply(path, g, **kwargs)
    back, report = read_gaussians_ply(path, on_invalid="report")
    assert report.num_output == n
    expected = dict(g.extras)
    assert set(back.extras) == set(expected)
    back_ordered = Gaussians(back.means, back.quats, back.log_scales, back.opacity_logits, back.sh,
                             {k: back.extras[k] for k in expected})
    assert_same_gaussians(g, back_ordered)
    assert back.sh_degree == degree
    # our own file, re-written with the same options: byte-identical
    again = path.with_name("again.ply")
    write_gaussians_ply(again, back, **kwargs)
    assert again.read_bytes() == path.read_bytes()
    # the fast reader agrees with the plyfile reference on every format
    fast, slow = read_vertex_table(path), read_vertex_table_plyfile(path)
    assert fast.dtype.names == slow.dtype.names
    for name in fast.dtype.names:
        np.testing.assert_array_equal(fast[name], slow[name])


def test_round_trip_binary_keeps_nan_bits(tmp_path):
    g = random_gaussians(4, 1)
    g.sh[2, 1, 0] = np.float32("nan")
    g.means[3, 0] = np.float32("inf")
    for endian in "<>":
        write_gaussians_ply(tmp_path / "g.ply", g, endian=endian)
        back, report = read_gaussians_ply(tmp_path / "g.ply", on_invalid="report")
        assert_same_gaussians(g, back)
        assert report.issues == {"non_finite": {"x": 1, "f_rest_0": 1}}


def test_foreign_layout_value_identical(tmp_path):
    """A foreign file (double positions, extras between standard properties, comments) keeps its values."""
    rng = np.random.default_rng(1)
    n = 7
    fields = ([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("label", "<u2")] + [(f"f_dc_{c}", "<f4") for c in range(3)]
              + [(f"f_rest_{i}", "<f4") for i in range(9)] + [("opacity", "<f4")]
              + [(f"scale_{i}", "<f4") for i in range(3)] + [(f"rot_{i}", "<f4") for i in range(4)]
              + [("semantic", "<u2")])
    table = np.zeros(n, dtype=fields)
    for name in table.dtype.names:
        table[name] = rng.integers(0, 9, n) if table.dtype[name].kind == "u" else rng.normal(size=n)
    for axis in "xyz":  # doubles holding float32 values: read as float32 without loss
        table[axis] = table[axis].astype(np.float32)
    write_vertex_table(tmp_path / "foreign.ply", table, fmt="binary_big_endian", comments=("made elsewhere",))
    g, _ = read_gaussians_ply(tmp_path / "foreign.ply")
    assert g.sh_degree == 1
    np.testing.assert_array_equal(g.means[:, 0], table["x"].astype(np.float32))
    np.testing.assert_array_equal(g.sh[:, 1, 0], table["f_rest_0"])  # channel-major
    np.testing.assert_array_equal(g.sh[:, 1, 1], table["f_rest_3"])
    np.testing.assert_array_equal(g.sh[:, 3, 2], table["f_rest_8"])
    assert g.extras["label"].dtype == np.uint16 and g.extras["semantic"].dtype == np.int32
    np.testing.assert_array_equal(g.extras["semantic"], table["semantic"])
    write_gaussians_ply(tmp_path / "ours.ply", g)
    back = read_vertex_table(tmp_path / "ours.ply")
    for name in table.dtype.names:
        np.testing.assert_array_equal(back[name], table[name])
    header = read_ply_header(tmp_path / "ours.ply")
    assert [p.dtype for p in header.element("vertex").properties if p.name == "semantic"] == ["i4"]


def test_empty_gaussians_round_trip(tmp_path):
    for binary in (True, False):
        write_gaussians_ply(tmp_path / "e.ply", Gaussians.empty(2), binary=binary)
        g, report = read_gaussians_ply(tmp_path / "e.ply")
        assert len(g) == 0 and g.sh_degree == 2 and report.ok


# --------------------------------------------------------------------------------------------
# malformed inputs
# --------------------------------------------------------------------------------------------
def _header(n, names, fmt="binary_little_endian", extra=""):
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {n}"] + [f"property float {p}" for p in names]
    return ("\n".join(lines) + "\n" + extra + "end_header\n").encode()


STANDARD_SH0 = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]


def _body(n, names, seed=0):
    return np.random.default_rng(seed).normal(size=(n, len(names))).astype("<f4").tobytes()


def assert_clean_error(path, *needles, on_invalid="error"):
    with pytest.raises(PlyFormatError) as info:
        read_gaussians_ply(path, on_invalid=on_invalid)
    message = str(info.value)
    assert str(path) in message, message
    for needle in needles:
        assert needle in message, message
    # the error comes from our code, not from inside numpy or plyfile
    assert "seggaussian" in str(info.traceback[-1].path)
    assert info.value.__cause__ is None and (info.value.__context__ is None or info.value.__suppress_context__)
    return message


@pytest.mark.parametrize(
    "name, content, needles",
    [
        ("empty", b"", ["empty file"]),
        ("not_ply", b"solid cube\nfacet normal 0 0 1\n", ["not a PLY file"]),
        ("no_end_header", _header(2, STANDARD_SH0)[:-11], ["end_header"]),
        ("truncated_body", _header(3, STANDARD_SH0) + _body(3, STANDARD_SH0)[:-5], ["truncated", "3 vertices",
                                                                                    "2 complete"]),
        ("count_larger", _header(1000, STANDARD_SH0) + _body(10, STANDARD_SH0), ["truncated", "1000 vertices"]),
        ("missing_opacity", _header(2, [p for p in STANDARD_SH0 if p != "opacity"])
         + _body(2, STANDARD_SH0[:-1]), ["'opacity'", "missing"]),
        ("f_rest_7", _header(2, STANDARD_SH0 + [f"f_rest_{i}" for i in range(7)])
         + _body(2, STANDARD_SH0 + ["r"] * 7), ["7 f_rest_*"]),
        ("list_property", _header(1, STANDARD_SH0, extra="property list uchar int vertex_indices\n")
         + _body(1, STANDARD_SH0) + b"\x01\x00\x00\x00\x00", ["'vertex_indices'", "list property"]),
        ("unknown_type", _header(1, STANDARD_SH0, extra="property float128 q\n"), ["unknown PLY type"]),
        ("no_vertex", b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", ["no 'vertex' element"]),
        ("ascii_short", _header(3, STANDARD_SH0, fmt="ascii") + b"1 " * 14 + b"\n" + b"2 " * 14 + b"\n",
         ["truncated", "3 vertices", "2 vertex lines"]),
        ("ascii_bad_line", _header(2, STANDARD_SH0, fmt="ascii") + b"1 " * 14 + b"\n" + b"2 " * 13 + b"\n",
         ["vertex line 1 has 13 values"]),
        ("ascii_word", _header(1, STANDARD_SH0, fmt="ascii") + b"1 " * 13 + b"abc\n", ["not a number"]),
        ("duplicate", _header(1, STANDARD_SH0 + ["x"]) + _body(1, STANDARD_SH0 + ["x"]), ["more than once"]),
    ],
)
def test_malformed_inputs_give_clean_errors(tmp_path, name, content, needles):
    path = tmp_path / f"{name}.ply"
    path.write_bytes(content)
    assert_clean_error(path, *needles)


def test_missing_file_clean_error(tmp_path):
    assert_clean_error(tmp_path / "nope.ply", "cannot read")


@pytest.mark.parametrize("binary", [True, False])
def test_nan_inf_rows_error_names_property_and_rows(tmp_path, binary):
    g = random_gaussians(10, 2)
    g.means[[1, 4], 1] = np.nan
    g.sh[7, 3, 1] = np.inf
    path = tmp_path / "bad.ply"
    write_gaussians_ply(path, g, binary=binary)
    message = assert_clean_error(path, "non finite", "y (2 rows)", "f_rest_10 (1 rows)")
    assert "--on-invalid" in message


# --------------------------------------------------------------------------------------------
# validation policies
# --------------------------------------------------------------------------------------------
def invalid_gaussians():
    """12 Gaussians, degree 1, with one kind of problem per row (rows 0..7), rows 8..11 clean."""
    g = random_gaussians(12, 1, seed=3, extras={"d": np.arange(12, dtype=np.float32)})
    g.means[0, 2] = np.nan                       # non-finite mean -> dropped
    g.quats[1] = 0.0                             # zero quaternion -> identity
    g.quats[2, 3] = np.inf                       # non-finite quaternion -> identity
    g.log_scales[3, 0] = 100.0                   # overflow -> clamp 88
    g.log_scales[4, 1] = np.nan                  # NaN scale -> dropped
    g.opacity_logits[5] = -40.0                  # saturated -> clamp -17
    g.sh[6, 2, 0] = np.nan                       # f_rest_1 -> zeroed
    g.extras["d"][7] = np.inf                    # float extra -> dropped
    return g


def test_validation_counts_every_problem():
    _, report = validate_gaussians(invalid_gaussians(), on_invalid="report", source="mem")
    assert report.issues == {
        "non_finite": {"z": 1, "f_rest_1": 1, "scale_1": 1, "rot_3": 1, "d": 1},
        "zero_norm_quaternion": {"rot": 1},
        "log_scale_overflow": {"scale_0": 1},
        "opacity_saturated": {"opacity": 1},
    }
    assert report.actions == {} and report.num_output == 12


def test_validation_error_names_everything():
    with pytest.raises(ValueError, match=r"mem: .*z \(1 rows\).*zero norm quaternion: rot \(1 rows\)"):
        validate_gaussians(invalid_gaussians(), source="mem")


def test_validation_drop():
    g = invalid_gaussians()
    out, report = validate_gaussians(g, on_invalid="drop", source="mem")
    assert len(out) == 4 and report.num_dropped == 8 and report.num_output == 4
    np.testing.assert_array_equal(out.extras["d"], [8, 9, 10, 11])
    assert sum(report.actions["dropped"].values()) == 8
    _, again = validate_gaussians(out, on_invalid="error")
    assert again.ok


def test_validation_repair():
    g = invalid_gaussians()
    out, report = validate_gaussians(g, on_invalid="repair", source="mem")
    assert report.num_dropped == 3 and len(out) == 9
    assert report.actions == {
        "dropped": {"z": 1, "scale_1": 1, "d": 1},
        "set_identity": {"rot": 2},
        "clamped": {"scale_0": 1, "opacity": 1},
        "zeroed": {"f_rest_1": 1},
    }
    np.testing.assert_array_equal(out.extras["d"], [1, 2, 3, 5, 6, 8, 9, 10, 11])
    np.testing.assert_array_equal(out.quats[0], [1, 0, 0, 0])  # former row 1
    np.testing.assert_array_equal(out.quats[1], [1, 0, 0, 0])  # former row 2
    assert out.log_scales[2, 0] == LOG_SCALE_FLOAT32_MAX
    assert out.opacity_logits[3] == -OPACITY_LOGIT_SATURATION
    assert out.sh[4, 2, 0] == 0.0
    np.testing.assert_array_equal(out.sh[5:], g.sh[8:])  # untouched rows unchanged
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.isfinite(getattr(out, name)).all()
    assert np.isfinite(out.scales()).all()
    _, again = validate_gaussians(out)
    assert again.ok


def test_validation_on_empty_and_bad_policy():
    out, report = validate_gaussians(Gaussians.empty(3))
    assert len(out) == 0 and report.ok
    with pytest.raises(ValueError, match="on_invalid"):
        validate_gaussians(Gaussians.empty(0), on_invalid="ignore")


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------
def test_atomic_write_leaves_old_file_and_no_temp(tmp_path):
    target = tmp_path / "scene.ply"
    target.write_bytes(b"old")

    def chunks():
        yield b"partial"
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        write_atomic(target, chunks())
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_write_rejects_unwritable_extras_before_touching_disk(tmp_path):
    g = random_gaussians(3, 0, extras={"name": np.array(["a", "b", "c"])})
    with pytest.raises(TypeError, match="name"):
        write_gaussians_ply(tmp_path / "x.ply", g)
    g = random_gaussians(3, 0, extras={"scale_0": np.zeros(3, np.float32)})
    with pytest.raises(ValueError, match="collides"):
        write_gaussians_ply(tmp_path / "x.ply", g)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------------
def test_cli_import_and_inspect(tmp_path):
    from click.testing import CliRunner

    from cli.seggaussian_cli import main

    g = invalid_gaussians()
    src = tmp_path / "scene.ply"
    write_gaussians_ply(src, g, binary=False)
    runner = CliRunner()
    result = runner.invoke(main, ["import", str(src), "--out", str(tmp_path / "out")])
    assert result.exit_code != 0 and "non finite" in result.output and str(src) in result.output
    assert not (tmp_path / "out" / "scene.ply").exists()

    result = runner.invoke(main, ["import", str(src), "--out", str(tmp_path / "out"), "--on-invalid", "repair",
                                  "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["num_gaussians"] == 9 and payload["validation"]["num_dropped"] == 3
    written, report = read_gaussians_ply(tmp_path / "out" / "scene.ply")
    assert len(written) == 9 and report.ok
    on_disk = json.loads((tmp_path / "out" / "scene.import.json").read_text())
    assert on_disk["validation"]["actions"]["set_identity"] == {"rot": 2}

    result = runner.invoke(main, ["inspect", str(src), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    assert info["num_gaussians"] == 12 and info["sh_degree"] == 1 and info["format"] == "ascii"
    assert info["validation"]["issues"]["zero_norm_quaternion"] == {"rot": 1}
    assert "INVALID" in info["summary"]

    result = runner.invoke(main, ["inspect", str(tmp_path / "out" / "scene.ply")])
    assert result.exit_code == 0 and result.output.strip().splitlines()[-1].endswith("valid")

    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"hello")
    result = runner.invoke(main, ["inspect", str(bad)])
    assert result.exit_code != 0 and "not a PLY file" in result.output and "Traceback" not in result.output


def test_other_elements_before_and_after_vertex(tmp_path):
    """A fixed-size element before the vertices is skipped; elements after them are ignored."""
    g = random_gaussians(5, 1, seed=9)
    write_gaussians_ply(tmp_path / "plain.ply", g)
    plain = (tmp_path / "plain.ply").read_bytes()
    end = plain.index(b"end_header\n")
    header = plain[:end].replace(b"element vertex", b"element camera 2\nproperty double fx\nproperty uchar id\n"
                                 b"element vertex")
    header += b"element face 1\nproperty list uchar int vertex_indices\n"
    body = plain[end + len(b"end_header\n"):]
    cameras = np.zeros(2, dtype=[("fx", "<f8"), ("id", "u1")]).tobytes()
    faces = b"\x03" + np.arange(3, dtype="<i4").tobytes()
    path = tmp_path / "mixed.ply"
    path.write_bytes(header + b"end_header\n" + cameras + body + faces)
    back, _ = read_gaussians_ply(path)
    assert_same_gaussians(g, back)
    assert read_vertex_table(path).tobytes() == read_vertex_table_plyfile(path).tobytes()


def reference_vertex_values(g: Gaussians) -> dict[str, np.ndarray]:
    """Slow, obviously-correct layout: property name -> column, one coefficient at a time."""
    k = g.num_sh_coeffs
    out = {axis: g.means[:, i] for i, axis in enumerate("xyz")}
    for c in range(3):
        out[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(1, k):
            out[f"f_rest_{c * (k - 1) + j - 1}"] = g.sh[:, j, c]
    out["opacity"] = g.opacity_logits
    for i in range(3):
        out[f"scale_{i}"] = g.log_scales[:, i]
    for i in range(4):
        out[f"rot_{i}"] = g.quats[:, i]
    return out


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_fast_table_layout_matches_reference(degree):
    from seggaussian.io.ply.reader import vertex_table_to_gaussians
    from seggaussian.io.ply.writer import gaussians_to_vertex_table

    g = random_gaussians(9, degree, seed=degree, extras={"semantic": np.arange(9, dtype=np.int64)})
    table = gaussians_to_vertex_table(g, normals=True)
    expected = reference_vertex_values(g)
    for name, column in expected.items():
        np.testing.assert_array_equal(table[name], column, err_msg=name)
    np.testing.assert_array_equal(table["nx"], 0)
    assert table.dtype["semantic"] == np.dtype("=i4")
    # view path (native, contiguous) and copy path (big-endian, strided) give the same Gaussians
    fast = vertex_table_to_gaussians(table)
    swapped = table.astype(table.dtype.newbyteorder(">"))
    strided = np.repeat(table, 2)[::2]  # every record once, non-contiguous
    for other in (swapped, strided):
        slow = vertex_table_to_gaussians(other)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            assert getattr(slow, name).tobytes() == getattr(fast, name).tobytes(), name


def test_validation_large_finite_sh_is_not_reported():
    """The all-finite fast path (a sum) overflows for huge finite values; the exact check must decide."""
    g = random_gaussians(4, 1)
    g.sh[:, :, :] = np.float32(3e38)
    _, report = validate_gaussians(g)
    assert report.ok
    g.sh[2, 3, 1] = -np.inf
    _, report = validate_gaussians(g, on_invalid="report")
    assert report.issues == {"non_finite": {"f_rest_5": 1}}


def test_cli_inspect_dataset_folder_delegates(tmp_path, monkeypatch):
    import sys
    import types

    from click.testing import CliRunner

    from cli.seggaussian_cli import main

    calls = []
    fake = types.ModuleType("seggaussian.shards")
    fake.inspect_dataset = lambda path, verify=False: calls.append(path) or {"summary": f"dataset {path}: 3 scenes", "scenes": 3}
    monkeypatch.setitem(sys.modules, "seggaussian.shards", fake)
    (tmp_path / "manifest.json").write_text("{}")
    result = CliRunner().invoke(main, ["inspect", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["scenes"] == 3 and calls == [tmp_path]
    result = CliRunner().invoke(main, ["inspect", str(tmp_path / ".."), "--json"])
    assert result.exit_code != 0 and "manifest.json" in result.output
