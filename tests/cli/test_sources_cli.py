"""``seggaussian synth`` end to end on a tiny configuration."""

from __future__ import annotations

import json

from click.testing import CliRunner

from cli.seggaussian_cli import main
from seggaussian.sources import replica, scannetpp


def test_synth_cli_both_layouts_json(tmp_path):
    out = tmp_path / "raw"
    result = CliRunner().invoke(main, ["synth", "--out", str(out), "--scenes", "2", "--seed", "1", "--width", "40",
                                       "--views", "2", "--max-edge", "0.25", "--json"])
    assert result.exit_code == 0, result.output
    payload = json.loads(result.output)
    assert len(payload["scenes"]["scannetpp"]) == 2 and len(payload["scenes"]["replica"]) == 1
    assert payload["summary"].startswith("synth: wrote 3 scenes")
    assert scannetpp.list_scenes(out / "scannetpp") == sorted(payload["scenes"]["scannetpp"])
    assert replica.list_scenes(out / "replica") == payload["scenes"]["replica"]
    assert scannetpp.list_scenes(out / "scannetpp", "nvs_sem_val") == [payload["scenes"]["scannetpp"][1]]


def test_synth_cli_single_layout_text(tmp_path):
    result = CliRunner().invoke(main, ["synth", "--out", str(tmp_path / "r"), "--scenes", "1", "--layout", "replica",
                                       "--width", "40", "--views", "1", "--max-edge", "0.25", "--no-progress"])
    assert result.exit_code == 0, result.output
    assert result.output.strip().splitlines()[-1].startswith("synth: wrote 1 scene (1 replica)")
    assert (tmp_path / "r" / "synroom0_s0" / "habitat" / "mesh_semantic.ply").is_file()


def test_synth_cli_height_sets_the_scannetpp_image_size(tmp_path):
    """--height: the ScanNet++ images and cameras at width x height (876 x 584 is ScanNet++'s DSLR size), read back
    through the reader; without it the height is 3/4 of the width."""
    from PIL import Image

    sizes = {}
    for name, extra in (("given", ["--height", "26"]), ("default", [])):
        out = tmp_path / name
        result = CliRunner().invoke(main, ["synth", "--out", str(out), "--scenes", "1", "--layout", "scannetpp",
                                           "--width", "40", "--views", "1", "--max-edge", "0.25", "--no-progress",
                                           *extra])
        assert result.exit_code == 0, result.output
        (scene_id,) = scannetpp.list_scenes(out)
        view = scannetpp.read_scene(out, scene_id).views[0]
        with Image.open(view.image_path) as image:
            sizes[name] = (view.camera.width, view.camera.height, image.size)
    assert sizes == {"given": (40, 26, (40, 26)), "default": (40, 30, (40, 30))}
    refused = CliRunner().invoke(main, ["synth", "--out", str(tmp_path / "x"), "--height", "8"])
    assert refused.exit_code == 2 and "--height" in refused.output
