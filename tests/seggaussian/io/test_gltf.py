"""glTF splats (``KHR_gaussian_splatting``): what our writer stores, read back by a parser written here from the glTF
2.0 specification and the extension's text (not by our reader), checked against their conventions; our reader on
files it did not write (quantized attributes, node transforms, external buffers); one-line refusals of files that
break the extension; round trips; a real splat converted to ``.glb`` and back; the ``.glb`` another implementation
(@playcanvas/splat-transform) writes."""

from __future__ import annotations

import base64
import json
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

from shared_data import WEB_SPLATS
from seggaussian.core.constants import SH_C0
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import detect_format, read_gaussians, read_gaussians_raw, write_gaussians
from seggaussian.io.gltf import decode_gltf, read_gltf, write_gltf
from seggaussian.io.splat_common import SplatFormatError

ROOT = Path(__file__).resolve().parents[3]
EXT = "KHR_gaussian_splatting"
#: glTF's frame in RDF terms, from the glTF 2.0 specification ("+Y is up; the front of an asset faces +Z, its left
#: side +X") read as a camera-like scene (RDF: x right, y down, z forward): up is -y, forward +z, so x is negated too
#: (a right-handed frame): glTF = diag(-1, -1, 1) RDF.
GLTF_FROM_RDF = np.diag([-1.0, -1.0, 1.0])
#: Component sizes and element widths of the glTF specification.
DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTHS = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}


def scene(n: int = 60, degree: int = 3, seed: int = 0, labels: bool = True) -> Gaussians:
    rng = np.random.default_rng(seed)
    extras = {"semantic": rng.integers(0, 20, n).astype(np.int32), "instance": rng.integers(0, 9, n).astype(np.int32)}
    return Gaussians.from_arrays(rng.uniform(-2, 2, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-5, 0, (n, 3)),
                                 rng.normal(size=n), rng.normal(0, 0.5, (n, (degree + 1) ** 2, 3)),
                                 extras if labels else None)


# --- an independent GLB parser (glTF 2.0, "Binary glTF Layout" and "Accessors") -------------------------------------
def parse_glb(data: bytes) -> tuple[dict, bytes]:
    magic, version, length = struct.unpack_from("<4sII", data)
    assert magic == b"glTF" and version == 2 and length == len(data)
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    doc = json.loads(data[20: 20 + json_length])
    bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
    assert bin_type == 0x004E4942 and bin_length % 4 == 0
    return doc, data[28 + json_length: 28 + json_length + bin_length]


def attribute(doc: dict, blob: bytes, semantic: str) -> np.ndarray:
    accessor = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][semantic]]
    view = doc["bufferViews"][accessor["bufferView"]]
    assert view["byteOffset"] % 4 == 0 and "byteStride" not in view
    width = WIDTHS[accessor["type"]]
    values = np.frombuffer(blob, DTYPES[accessor["componentType"]], accessor["count"] * width,
                           view["byteOffset"] + accessor.get("byteOffset", 0))
    return values.reshape(accessor["count"], width)


def rotation_matrices(wxyz: np.ndarray) -> np.ndarray:
    w, x, y, z = (wxyz / np.linalg.norm(wxyz, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def spec_colour(sh: dict, d: np.ndarray) -> np.ndarray:
    """The extension's "Calculating color from Spherical Harmonics", term by term (``sh[(l, m)]`` RGB ``[N, 3]``,
    ``d`` unit directions ``[N, 3]``)."""
    x, y, z = (d[:, i:i + 1] for i in range(3))
    c = sh[0, 0] * 0.2820947917738781
    c = c + sh[1, -1] * y * -0.4886025119029199 + sh[1, 0] * z * 0.4886025119029199 + sh[1, 1] * x * -0.4886025119029199
    c = (c + sh[2, -2] * x * y * 1.092548430592079 + sh[2, -1] * y * z * -1.092548430592079
         + sh[2, 0] * (2 * z * z - x * x - y * y) * 0.3153915652525200 + sh[2, 1] * x * z * -1.092548430592079
         + sh[2, 2] * (x * x - y * y) * 0.5462742152960395)
    c = (c + sh[3, -3] * y * (3 * x * x - y * y) * -0.5900435899266435 + sh[3, -2] * x * y * z * 2.890611442640554
         + sh[3, -1] * y * (4 * z * z - x * x - y * y) * -0.4570457994644657
         + sh[3, 0] * z * (2 * z * z - 3 * x * x - 3 * y * y) * 0.3731763325901154
         + sh[3, 1] * x * (4 * z * z - x * x - y * y) * -0.4570457994644657
         + sh[3, 2] * z * (x * x - y * y) * 1.445305721320277
         + sh[3, 3] * x * (x * x - 3 * y * y) * -0.5900435899266435)
    return c + 0.5


def test_written_glb_follows_the_extension(tmp_path):
    """Every stored attribute as the extension defines it, in glTF's frame: positions, xyzw unit rotations, linear
    scales, linear opacities, SH whose colour by the extension's own formulas equals ours, labels as ``_`` attributes
    of integer type, the frame glTF's (+Y up)."""
    import torch

    from seggaussian.render.sh import evaluate_sh

    g = scene()
    path = tmp_path / "s.glb"
    write_gaussians(path, g, legend={"semantic": {"names": ["a", "b"]}})
    doc, blob = parse_glb(path.read_bytes())
    assert doc["asset"]["version"] == "2.0" and EXT in doc["extensionsUsed"] and EXT not in doc.get(
        "extensionsRequired", [])
    primitive = doc["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 0
    assert primitive["extensions"][EXT]["kernel"] == "ellipse"
    assert primitive["extensions"][EXT]["colorSpace"] == "srgb_rec709_display"
    assert doc["extras"]["seggaussian"]["semantic"]["names"] == ["a", "b"]
    position = attribute(doc, blob, "POSITION")
    np.testing.assert_array_equal(position, g.means @ GLTF_FROM_RDF.T)
    pos_accessor = doc["accessors"][primitive["attributes"]["POSITION"]]
    np.testing.assert_allclose(pos_accessor["min"], position.min(0)), np.testing.assert_allclose(pos_accessor["max"],
                                                                                                  position.max(0))
    xyzw = attribute(doc, blob, f"{EXT}:ROTATION").astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(xyzw, axis=1), 1.0, atol=1e-6)
    stored = rotation_matrices(xyzw[:, [3, 0, 1, 2]])
    np.testing.assert_allclose(stored, GLTF_FROM_RDF @ rotation_matrices(g.quats.astype(np.float64)) @ GLTF_FROM_RDF,
                               atol=1e-6)
    np.testing.assert_allclose(attribute(doc, blob, f"{EXT}:SCALE"), np.exp(g.log_scales), rtol=1e-6)
    np.testing.assert_allclose(attribute(doc, blob, f"{EXT}:OPACITY")[:, 0], 1 / (1 + np.exp(-g.opacity_logits)),
                               rtol=1e-6)
    sh = {(l, m): attribute(doc, blob, f"{EXT}:SH_DEGREE_{l}_COEF_{m + l}").astype(np.float64)
          for l in range(4) for m in range(-l, l + 1)}
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(len(g), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ours = evaluate_sh(torch.from_numpy(g.sh.astype(np.float64)), torch.from_numpy(dirs), 3).numpy() + 0.5
    np.testing.assert_allclose(spec_colour(sh, dirs @ GLTF_FROM_RDF.T), ours, atol=1e-5)
    # up: a Gaussian above another in RDF (smaller y) is higher in glTF (larger Y)
    assert np.all(np.sign(position[:, 1]) == -np.sign(g.means[:, 1]))
    for name in ("semantic", "instance"):
        accessor = doc["accessors"][primitive["attributes"][f"_{name.upper()}"]]
        assert accessor["componentType"] in (5121, 5123, 5120, 5122) and accessor["type"] == "SCALAR"
        np.testing.assert_array_equal(attribute(doc, blob, f"_{name.upper()}")[:, 0], g.extras[name])
    colour = attribute(doc, blob, "COLOR_0")
    srgb = np.clip(0.5 + SH_C0 * g.sh[:, 0], 0, 1)
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    assert np.abs(colour[:, :3] / 255.0 - linear).max() <= 0.5 / 255 + 1e-6


@pytest.mark.parametrize(("suffix", "compression"), [(".glb", "none"), (".gltf", "none"), (".glb", "spz")])
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip(tmp_path, suffix, compression, degree):
    g = scene(degree=degree)
    path = tmp_path / f"s{suffix}"
    write_gaussians(path, g, gltf_compression=compression, legend={"semantic": {"names": ["x"]}})
    assert detect_format(path) == "gltf"
    back = read_gltf(path)
    h = back.gaussians
    assert back.legend == {"semantic": {"names": ["x"]}}
    assert set(h.extras) == {"semantic", "instance"}
    for name in h.extras:
        np.testing.assert_array_equal(h.extras[name], g.extras[name])
    if compression == "none":  # float attributes: exact up to exp/log and sigmoid/logit rounding
        np.testing.assert_array_equal(h.means, g.means)
        np.testing.assert_array_equal(h.sh, g.sh)
        np.testing.assert_allclose(h.quats, g.normalized_quats(), atol=1e-7)
        np.testing.assert_allclose(h.log_scales, g.log_scales, atol=1e-6)
        np.testing.assert_allclose(h.opacities(), g.opacities(), atol=1e-6)
    else:  # SPZ's quantization steps (seggaussian/io/spz.py)
        np.testing.assert_allclose(h.means, g.means, atol=2e-3)
        np.testing.assert_allclose(rotation_matrices(h.quats.astype(np.float64)),  # version 2: 8-bit x, y, z; w derived
                                   rotation_matrices(g.quats.astype(np.float64)), atol=0.15)
        np.testing.assert_allclose(h.log_scales, g.log_scales, atol=0.05)
        np.testing.assert_allclose(h.opacities(), g.opacities(), atol=0.003)
        np.testing.assert_allclose(h.sh[:, 0], g.sh[:, 0], atol=0.02)
        np.testing.assert_allclose(h.sh[:, 1:], np.clip(g.sh[:, 1:], -1, 1), atol=0.07)  # SPZ stores [-1, 1]


# --- files our writer does not make ----------------------------------------------------------------------------------
def handmade(attributes: dict, *, n: int = 3, node: dict | None = None, extension: dict | None = None,
             required: list | None = None, mode: int = 0, binary: bool = True) -> bytes:
    """A splat glTF from ``{semantic: (array [n, w], component type, type, normalized)}``, views packed 4-aligned."""
    blob, views, accessors, attrs = bytearray(), [], [], {}
    for semantic, (values, ctype, kind, normalized) in attributes.items():
        data = np.ascontiguousarray(values, DTYPES[ctype]).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data)})
        blob += data + b"\0" * (-len(data) % 4)
        accessors.append({"bufferView": len(views) - 1, "componentType": ctype, "count": n, "type": kind,
                          **({"normalized": True} if normalized else {})})
        attrs[semantic] = len(accessors) - 1
    ext = extension if extension is not None else {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}
    doc = {"asset": {"version": "2.0"}, "extensionsUsed": [EXT], "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0, **(node or {})}],
           "meshes": [{"primitives": [{"attributes": attrs, "mode": mode, "extensions": {EXT: ext}}]}],
           "buffers": [{"byteLength": len(blob)}], "bufferViews": views, "accessors": accessors}
    if required is not None:
        doc["extensionsRequired"] = required
    if not binary:
        doc["buffers"][0]["uri"] = "data:application/gltf-buffer;base64," + base64.b64encode(bytes(blob)).decode()
        return json.dumps(doc, indent=1).encode()
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    return (struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob)) + struct.pack("<II", len(text), 0x4E4F534A)
            + text + struct.pack("<II", len(blob), 0x004E4942) + bytes(blob))


def basic_attributes(n: int = 3) -> dict:
    rng = np.random.default_rng(5)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {"POSITION": (rng.uniform(-1, 1, (n, 3)), 5126, "VEC3", False),
            f"{EXT}:ROTATION": (q, 5126, "VEC4", False),
            f"{EXT}:SCALE": (rng.uniform(0.01, 0.2, (n, 3)), 5126, "VEC3", False),
            f"{EXT}:OPACITY": (rng.uniform(0.1, 0.9, (n, 1)), 5126, "SCALAR", False),
            f"{EXT}:SH_DEGREE_0_COEF_0": (rng.normal(size=(n, 3)), 5126, "VEC3", False)}


def test_reads_quantized_attributes_node_transforms_and_json_gltf():
    """Normalized short rotations, normalized byte opacities, unsigned short scales (allowed by the extension), a
    node's translation/rotation/scale (applied: positions, rotations, scales), and a .gltf with a data URI."""
    base = basic_attributes()
    plain = decode_gltf(handmade(base)).gaussians
    q16 = np.round(base[f"{EXT}:ROTATION"][0] * 32767)
    op8 = np.round(base[f"{EXT}:OPACITY"][0] * 255)
    sc16 = np.round(base[f"{EXT}:SCALE"][0] * 1000)
    quantized = dict(base, **{f"{EXT}:ROTATION": (q16, 5122, "VEC4", True),
                              f"{EXT}:OPACITY": (op8, 5121, "SCALAR", True),
                              f"{EXT}:SCALE": (sc16, 5123, "VEC3", False)})
    q = decode_gltf(handmade(quantized)).gaussians
    np.testing.assert_allclose(q.opacities(), op8[:, 0] / 255, atol=1e-6)
    np.testing.assert_allclose(np.exp(q.log_scales), sc16, rtol=1e-6)  # not normalized: the integers themselves
    np.testing.assert_allclose(rotation_matrices(q.quats.astype(np.float64)),
                               rotation_matrices(plain.quats.astype(np.float64)), atol=1e-3)
    # node: translate (1, 2, 3), turn 90 degrees about glTF's Y, scale 2
    s = np.sqrt(0.5)
    moved = decode_gltf(handmade(base, node={"translation": [1, 2, 3], "rotation": [0, s, 0, s],
                                             "scale": [2, 2, 2]})).gaussians
    turn = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    expected = (2 * base["POSITION"][0] @ turn.T + [1, 2, 3]) @ GLTF_FROM_RDF.T
    np.testing.assert_allclose(moved.means, expected, atol=1e-5)
    np.testing.assert_allclose(moved.log_scales, plain.log_scales + np.log(2), atol=1e-5)
    np.testing.assert_allclose(rotation_matrices(moved.quats.astype(np.float64)),
                               GLTF_FROM_RDF @ turn @ GLTF_FROM_RDF @ rotation_matrices(plain.quats.astype(np.float64)),
                               atol=1e-5)
    as_json = decode_gltf(handmade(base, binary=False)).gaussians
    np.testing.assert_array_equal(as_json.means, plain.means)


def test_external_buffer_beside_the_gltf(tmp_path):
    doc = json.loads(handmade(basic_attributes(), binary=False))
    blob = base64.b64decode(doc["buffers"][0]["uri"].split(",", 1)[1])
    (tmp_path / "data.bin").write_bytes(blob)
    doc["buffers"][0]["uri"] = "data.bin"
    (tmp_path / "s.gltf").write_text(json.dumps(doc))
    assert len(read_gaussians(tmp_path / "s.gltf").gaussians) == 3
    doc["buffers"][0]["uri"] = "../outside.bin"
    (tmp_path / "s.gltf").write_text(json.dumps(doc))
    with pytest.raises(SplatFormatError, match="outside the .gltf's folder"):
        read_gaussians(tmp_path / "s.gltf")
    doc["buffers"][0]["uri"] = "https://example.com/data.bin"
    (tmp_path / "s.gltf").write_text(json.dumps(doc))
    with pytest.raises(SplatFormatError, match="nothing is fetched"):
        read_gaussians(tmp_path / "s.gltf")


BREAKS = {
    "opacity above 1": (lambda a: a[f"{EXT}:OPACITY"][0].__setitem__((0, 0), 1.5), {}, "opacity outside"),
    "negative scale": (lambda a: a[f"{EXT}:SCALE"][0].__setitem__((1, 2), -0.1), {}, "negative or non-finite scale"),
    "non-unit rotation": (lambda a: a[f"{EXT}:ROTATION"][0].__setitem__(0, [0.0, 0.0, 0.0, 2.0]), {}, "not a unit"),
    "log scales (negative)": (lambda a: a[f"{EXT}:SCALE"][0].__setitem__(slice(None), -3.0), {}, "scale"),
    "missing SH degree 1 coefficient": (lambda a: a.update({f"{EXT}:SH_DEGREE_1_COEF_0": a["POSITION"],
                                                            f"{EXT}:SH_DEGREE_1_COEF_2": a["POSITION"]}), {},
                                        "SH degree 1 is partly defined"),
    "triangles": (None, {"mode": 4}, "requires POINTS"),
    "linear colour space": (None, {"extension": {"kernel": "ellipse", "colorSpace": "lin_rec709_display"}},
                            "colorSpace"),
    "unknown kernel": (None, {"extension": {"kernel": "box", "colorSpace": "srgb_rec709_display"}}, "kernel"),
    # the draft before ratification, as CesiumJS's older test tiles hold it: _SCALE and _ROTATION, no kernel
    "pre-ratification draft": (lambda a: a.update({"_SCALE": a.pop(f"{EXT}:SCALE"), "_ROTATION": a.pop(f"{EXT}:ROTATION")}),
                               {"extension": {}}, "pre-ratification draft"),
    "unknown required extension": (None, {"required": ["EXT_meshopt_compression"]}, "extensionsRequired"),
    "mirroring node": (None, {"node": {"scale": [-1, 1, 1]}}, "reflection"),
    "shearing node": (None, {"node": {"scale": [1, 2, 1]}}, "not a uniform scale"),
}


@pytest.mark.parametrize("case", list(BREAKS))
def test_files_breaking_the_extension_are_refused_in_one_line(tmp_path, case):
    change, options, message = BREAKS[case]
    attributes = basic_attributes()
    if change is not None:
        change(attributes)
    path = tmp_path / "bad.glb"
    path.write_bytes(handmade(attributes, **options))
    with pytest.raises(SplatFormatError) as info:
        read_gaussians_raw(path)
    text = str(info.value)
    assert message in text and str(path) in text and "\n" not in text


def test_not_a_splat_and_broken_containers(tmp_path):
    path = tmp_path / "mesh.glb"
    attributes = basic_attributes()
    data = handmade(attributes).replace(EXT.encode(), b"KHR_xaussian_splatting")
    path.write_bytes(data)
    with pytest.raises(SplatFormatError, match="no mesh primitive carries"):
        read_gaussians(path)
    good = handmade(attributes)
    for cut in (8, 20, 100, len(good) - 4):
        path.write_bytes(good[:cut])
        with pytest.raises(SplatFormatError, match=str(path)):
            read_gaussians(path)


def test_convert_refuses_unwritable(tmp_path):
    from seggaussian.io.converting import ConvertConfig, convert_splat

    g = scene(degree=3)
    src = tmp_path / "s.glb"
    write_gltf(src, g)
    with pytest.raises(ValueError, match=r"antimatter15 .splat cannot hold SH degree 3 .* and the per-Gaussian "
                                         r"columns instance, semantic"):
        convert_splat(src, tmp_path / "s.splat")
    assert not (tmp_path / "s.splat").exists()
    result = convert_splat(src, tmp_path / "s.splat", ConvertConfig(drop=True))
    assert result.dropped == {"sh_degree": [3, 0], "extras": ["instance", "semantic"]}
    result = convert_splat(src, tmp_path / "back.ply")
    assert result.dropped == {} and result.sh_degree == 3
    again = convert_splat(tmp_path / "back.ply", tmp_path / "again.glb")
    assert again.in_format == "ply" and again.out_format == "gltf"
    h = read_gltf(tmp_path / "again.glb").gaussians
    np.testing.assert_array_equal(h.extras["semantic"], g.extras["semantic"])
    np.testing.assert_allclose(h.means, g.means)


@pytest.mark.parametrize("name", ["guitar.compressed.ply", "splat_transform_fixtures/minimal.splat"])
def test_real_splat_to_glb_and_back_keeps_its_gaussians(tmp_path, name):
    """A real file (shared/realdata/web_splats) -> .glb -> its own format: the same Gaussians as read from it."""
    from seggaussian.io.converting import convert_splat

    source = WEB_SPLATS / name
    if not source.is_file():
        pytest.skip(f"{source} absent (shared real data not mounted)")
    original, _, fmt = read_gaussians(source)
    convert_splat(source, tmp_path / "scene.glb")
    suffix = ".compressed.ply" if fmt == "compressed_ply" else ".splat"
    convert_splat(tmp_path / "scene.glb", tmp_path / f"back{suffix}")
    via_glb, _, _ = read_gaussians(tmp_path / "scene.glb")
    back, _, back_fmt = read_gaussians(tmp_path / f"back{suffix}")
    assert back_fmt == fmt and len(back) == len(original) == len(via_glb)
    np.testing.assert_array_equal(via_glb.means, original.means)
    np.testing.assert_array_equal(via_glb.sh, original.sh)
    np.testing.assert_allclose(via_glb.log_scales, original.log_scales, atol=1e-5)
    np.testing.assert_allclose(via_glb.opacities(), original.opacities(), atol=1e-6)
    np.testing.assert_allclose(via_glb.quats, original.normalized_quats(), atol=1e-6)
    if fmt == "splat":  # its 8-bit fields come back as they were, its floats within float32 rounding
        from seggaussian.io.splat import SPLAT_RECORD

        a, b = (np.frombuffer(p.read_bytes(), SPLAT_RECORD) for p in (source, tmp_path / "back.splat"))
        np.testing.assert_array_equal(a["rgba"], b["rgba"]), np.testing.assert_array_equal(a["rot"], b["rot"])
        np.testing.assert_array_equal(a["position"], b["position"])
        np.testing.assert_allclose(a["scale"], b["scale"], rtol=1e-6)
    else:  # the same file as written from the original (the writer's Morton order and quantization)
        direct = tmp_path / f"direct{suffix}"
        write_gaussians(direct, original)
        expected, _, _ = read_gaussians(direct)
        np.testing.assert_array_equal(back.means, expected.means)
        np.testing.assert_allclose(back.sh, expected.sh, atol=1e-6)


SPLAT_TRANSFORM = ROOT / ".node" / "node_modules" / "@playcanvas" / "splat-transform" / "bin" / "cli.mjs"


@pytest.mark.skipif(shutil.which("node") is None or not SPLAT_TRANSFORM.is_file(),
                    reason=f"@playcanvas/splat-transform not installed ({SPLAT_TRANSFORM} missing or no node); run "
                           "`make setup` with node/npm")
@pytest.mark.parametrize("degree", [0, 3])
def test_splat_transform_glb_reads_as_its_ply(tmp_path, degree):
    """A .glb written by another implementation (@playcanvas/splat-transform 3.7.0's KHR_gaussian_splatting writer,
    which turns PLY data by 180 degrees about z into glTF's frame, as we do) reads back as the PLY it was made from.
    It copies a PLY's quaternions as they are: from non-unit ones (as 3DGS trainers save them) it writes a file the
    extension forbids ("unit quaternions"), which is refused in one line."""
    g = scene(n=200, degree=degree, labels=False)
    g = Gaussians(g.means, g.normalized_quats(), g.log_scales, g.opacity_logits, g.sh)
    glb = tmp_path / "s.glb"
    for quats in ("unit", "raw"):
        ply = tmp_path / f"{quats}.ply"
        write_gaussians(ply, g if quats == "unit" else Gaussians(g.means, g.quats * 3, g.log_scales, g.opacity_logits,
                                                                  g.sh))
        result = subprocess.run(["node", str(SPLAT_TRANSFORM), "-q", "-w", str(ply), str(glb)], capture_output=True,
                                text=True, timeout=120)
        assert result.returncode == 0 and glb.is_file(), result.stderr[-2000:]
        if quats == "raw":
            with pytest.raises(SplatFormatError, match=r"ROTATION: 200 Gaussians have a rotation that is not a unit"):
                read_gaussians(glb)
            continue
        h, _, fmt = read_gaussians(glb)
        assert fmt == "gltf" and len(h) == len(g) and h.sh_degree == degree
        np.testing.assert_allclose(h.means, g.means, atol=1e-6)
        # it turns the rotations by left-multiplying (R -> F R), we conjugate (F R F): the same covariance
        np.testing.assert_allclose(h.covariances(), g.covariances(), atol=1e-6, rtol=1e-5)
        np.testing.assert_allclose(h.log_scales, g.log_scales, atol=1e-5)
        np.testing.assert_allclose(h.opacities(), g.opacities(), atol=1e-6)
        np.testing.assert_allclose(h.sh, g.sh, atol=1e-5)
