"""``seggaussian convert IN OUT``: every written format from one glTF file and back, the target picked by the name;
a one-line refusal of what the target cannot hold, ``--drop`` counted in the summary; ``--transform``; ``--json``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from cli.seggaussian_cli import main
from seggaussian.core.gaussians import Gaussians
from seggaussian.io.formats import read_gaussians, write_gaussians


def scene(degree: int = 2, labels: bool = True) -> Gaussians:
    rng = np.random.default_rng(3)
    n = 40
    extras = {"semantic": rng.integers(0, 5, n).astype(np.int32)} if labels else None
    return Gaussians.from_arrays(rng.uniform(-1, 1, (n, 3)), rng.normal(size=(n, 4)), rng.uniform(-4, -1, (n, 3)),
                                 rng.normal(size=n), rng.normal(0, 0.3, (n, (degree + 1) ** 2, 3)), extras)


def convert(*args: str):
    return CliRunner().invoke(main, ["convert", *map(str, args)])


@pytest.mark.parametrize("suffix", [".ply", ".compressed.ply", ".spz", ".ksplat", ".gltf", ".glb"])
def test_every_format_from_and_back_to_gltf(tmp_path, suffix):
    """glTF -> each format -> glTF: the output format follows the name, the input is detected by content."""
    g = scene(labels=False)
    source = tmp_path / "in.glb"
    write_gaussians(source, g)
    middle = tmp_path / f"mid{suffix}"
    result = convert(source, middle, "--json")
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert payload["in_format"] == "gltf" and payload["num_gaussians"] == len(g) and payload["dropped"] == {}
    back = tmp_path / "back.glb"
    result = convert(middle, back)
    assert result.exit_code == 0, result.output
    assert result.output.count("\n") == 1 and result.output.startswith(f"converted {len(g)} Gaussians (SH degree 2)")
    h, _, fmt = read_gaussians(back)
    assert fmt == "gltf" and len(h) == len(g) and h.sh_degree == 2
    np.testing.assert_allclose(np.sort(h.means, axis=0), np.sort(g.means, axis=0), atol=2e-3)


def test_refuses_what_the_target_cannot_hold_unless_dropped(tmp_path):
    source = tmp_path / "in.glb"
    write_gaussians(source, scene(degree=2))
    for target, what in (("out.splat", "SH degree 2"), ("out.spz", "semantic"), ("out.ksplat", "semantic")):
        result = convert(source, tmp_path / target)
        assert result.exit_code == 1 and not (tmp_path / target).exists()
        (line,) = result.output.strip().splitlines()
        assert line.startswith("Error:") and what in line and "--drop" in line, line
    result = convert(source, tmp_path / "out.splat", "--json")
    assert result.exit_code == 1 and "cannot hold" in json.loads(result.output)["error"]
    result = convert(source, tmp_path / "out.splat", "--drop")
    assert result.exit_code == 0, result.output
    assert "--drop: SH degree 2 cut to 0, columns semantic dropped" in result.output
    h, _, _ = read_gaussians(tmp_path / "out.splat")
    assert h.sh_degree == 0 and not h.extras
    # labels go through a glTF and a PLY, which hold them
    result = convert(source, tmp_path / "out.ply", "--json")
    assert result.exit_code == 0 and json.loads(result.output)["dropped"] == {}
    np.testing.assert_array_equal(read_gaussians(tmp_path / "out.ply").gaussians.extras["semantic"],
                                  scene(degree=2).extras["semantic"])  # what was written, not the glTF read back


def test_transform_and_refusals(tmp_path):
    g = scene(labels=False)
    source = tmp_path / "in.ply"
    write_gaussians(source, g)
    transform = tmp_path / "t.json"
    matrix = np.eye(4)
    matrix[:3, 3] = [1.0, 2.0, 3.0]
    transform.write_text(json.dumps({"world_from_splat": matrix.tolist()}))
    result = convert(source, tmp_path / "moved.glb", "--transform", transform)
    assert result.exit_code == 0 and "moved by" in result.output, result.output
    np.testing.assert_allclose(read_gaussians(tmp_path / "moved.glb").gaussians.means, g.means + [1, 2, 3], atol=1e-5)
    result = convert(source, source)
    assert result.exit_code == 1 and "overwrite the input" in result.output
    garbage = tmp_path / "junk.glb"
    garbage.write_bytes(b"glTF" + bytes(30))
    result = convert(garbage, tmp_path / "x.ply")
    assert result.exit_code == 1 and str(garbage) in result.output and "Traceback" not in result.output
    assert len(result.output.strip().splitlines()) == 1
