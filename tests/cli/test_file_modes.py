"""Under umask 022 every file a command writes is 0644 and every folder 0755 (never mkstemp's 0600/0700)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.ovgaussian_cli import main as ov_main
from cli.seggaussian_cli import main as seg_main
from cli_inputs import make_cli_inputs


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return make_cli_inputs(tmp_path_factory.mktemp("inputs"))


@pytest.fixture
def umask_022():
    previous = os.umask(0o022)
    yield
    os.umask(previous)


def _modes(folder: Path) -> dict[str, str]:
    """Relative path -> octal mode of every file and folder under ``folder`` (itself included)."""
    out = {".": oct(stat.S_IMODE(folder.stat().st_mode))}
    for p in folder.rglob("*"):
        out[str(p.relative_to(folder))] = oct(stat.S_IMODE(p.lstat().st_mode))
    return out


def _assert_umask_modes(folder: Path, min_files: int = 1):
    modes = _modes(folder)
    files = [p for p in folder.rglob("*") if p.is_file()]
    assert len(files) >= min_files, modes
    bad = {rel: mode for rel, mode in modes.items()
           if mode != ("0o755" if (folder / rel).is_dir() else "0o644")}
    assert not bad, bad
    assert not [p for p in folder.rglob(".*tmp-*")], "temporary files left"


def _run(cli, argv):
    result = CliRunner().invoke(cli, argv)
    assert result.exit_code == 0, (argv, result.output)
    return result


def test_modes_synth_import_render_fit_export_bench(inputs, tmp_path, umask_022):
    out = tmp_path / "synth"
    _run(seg_main, ["synth", "--out", str(out), "--scenes", "1", "--replica-scenes", "1", "--width", "32",
                    "--views", "2", "--no-progress"])
    _assert_umask_modes(out, min_files=10)
    out = tmp_path / "import"
    _run(seg_main, ["import", str(inputs["ply"]), "--out", str(out)])
    _assert_umask_modes(out, min_files=2)
    out = tmp_path / "convert"
    _run(seg_main, ["convert", str(inputs["ply"]), str(out / "c.glb")])
    _run(seg_main, ["convert", str(inputs["ply"]), str(out / "c.gltf"), "--gltf-compression", "spz"])
    _assert_umask_modes(out, min_files=2)
    out = tmp_path / "render"
    _run(seg_main, ["render", str(inputs["ply"]), "--out", str(out / "v.png"), "--width", "16", "--height", "16"])
    _assert_umask_modes(out)
    out = tmp_path / "fit"
    _run(seg_main, ["fit", "--root", str(inputs["raw"]), "--scene", inputs["scene_id"], "--out", str(out / "f.ply"),
                    "--iterations", "2", "--no-progress"])
    _assert_umask_modes(out, min_files=2)
    out = tmp_path / "export"
    _run(seg_main, ["export-ply", str(inputs["dataset"]), "--scene", "va0", "--out", str(out / "e.ply")])
    _assert_umask_modes(out)
    out = tmp_path / "bench"
    _run(seg_main, ["bench", "--from-json", str(inputs["bench_json"]), "--markdown", str(out / "b.md")])
    _assert_umask_modes(out)


def test_modes_build_and_split(inputs, tmp_path, umask_022):
    out = tmp_path / "dataset"
    _run(seg_main, ["build", "--root", str(inputs["raw"]), "--out", str(out), "--gaussians", "oracle",
                    "--oracle-gaussians", "200", "--no-progress"])
    _run(seg_main, ["split", "--data", str(out), "--reassign"])
    _assert_umask_modes(out, min_files=8)


def test_modes_train_bench_predict(inputs, tmp_path, umask_022):
    import shutil

    dataset = tmp_path / "dataset"
    shutil.copytree(inputs["dataset"], dataset)
    os.chmod(dataset, 0o755)
    run = tmp_path / "run"
    _run(ov_main, ["train", "--data", str(dataset), "--out", str(run), "--epochs", "1", "--model-preset", "slim",
                   "--pixels-per-view", "64", "--no-progress"])
    assert (run / "checkpoints" / "epoch-0001").is_dir()
    _run(ov_main, ["bench", "--data", str(dataset), "--predictor", "majority", "--out", str(run / "bench.json"),
                   "--no-progress"])
    _assert_umask_modes(run, min_files=6)
    out = tmp_path / "predict"
    _run(ov_main, ["predict", str(inputs["ply"]), "--run", str(inputs["run"]), "--vocab", "chair,table",
                   "--out", str(out / "p.ply")])
    _assert_umask_modes(out)
