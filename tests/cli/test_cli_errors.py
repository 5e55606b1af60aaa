"""Every command of both CLIs: an output under a file, a read-only output and a missing input each give
one line naming the path, exit status 1 and no traceback; with --json, ``{"error", "path"}`` on stdout."""

from __future__ import annotations

import builtins
import errno
import io
import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli.ovgaussian_cli import main as ov_main
from cli.seggaussian_cli import main as seg_main
from cli_inputs import make_cli_inputs


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return make_cli_inputs(tmp_path_factory.mktemp("inputs"))


class _ReadOnly:
    """A read-only folder. Permission bits do not stop root, so under root the same refusal (EACCES) is
    produced by refusing every new file or folder below it at the ``os`` level."""

    def __init__(self, path: Path, monkeypatch):
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        path.chmod(0o555)
        if os.geteuid() != 0:
            return
        real_open, real_mkdir, real_builtin_open = os.open, os.mkdir, builtins.open

        def inside(target) -> bool:
            try:
                return Path(os.fsdecode(target)).resolve().is_relative_to(path.resolve())
            except (TypeError, ValueError):
                return False

        def deny(target):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fsdecode(target))

        def guarded_open(target, flags, *args, **kwargs):
            if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and inside(target):
                deny(target)
            return real_open(target, flags, *args, **kwargs)

        def guarded_mkdir(target, *args, **kwargs):
            if inside(target):
                deny(target)
            return real_mkdir(target, *args, **kwargs)

        def guarded_builtin_open(file, mode="r", *args, **kwargs):
            if isinstance(file, (str, bytes, os.PathLike)) and set(mode) & set("wax+") and inside(file):
                deny(file)
            return real_builtin_open(file, mode, *args, **kwargs)

        monkeypatch.setattr(os, "open", guarded_open)
        monkeypatch.setattr(os, "mkdir", guarded_mkdir)
        monkeypatch.setattr(builtins, "open", guarded_builtin_open)
        monkeypatch.setattr(io, "open", guarded_builtin_open)


def _cases(i, where):
    """(cli, argv) per command; ``where`` is the output path to use (or the missing input)."""
    return {
        "synth": (seg_main, ["synth", "--out", str(where), "--scenes", "1", "--replica-scenes", "0",
                             "--width", "32", "--views", "2"]),
        "import": (seg_main, ["import", str(i["ply"]), "--out", str(where)]),
        "convert": (seg_main, ["convert", str(i["ply"]), str(where / "c.glb")]),
        "render": (seg_main, ["render", str(i["ply"]), "--out", str(where / "x.png"), "--width", "16",
                              "--height", "16"]),
        "fit": (seg_main, ["fit", "--root", str(i["raw"]), "--scene", i["scene_id"], "--out", str(where / "f.ply"),
                           "--iterations", "2"]),
        "build": (seg_main, ["build", "--root", str(i["raw"]), "--out", str(where), "--gaussians", "oracle",
                             "--oracle-gaussians", "200"]),
        "export-ply": (seg_main, ["export-ply", str(i["dataset"]), "--scene", "va0", "--out", str(where / "e.ply")]),
        "bench": (seg_main, ["bench", "--from-json", str(i["bench_json"]), "--markdown", str(where / "b.md")]),
        "train": (ov_main, ["train", "--data", str(i["dataset"]), "--out", str(where), "--epochs", "1"]),
        "ov-bench": (ov_main, ["bench", "--data", str(i["dataset"]), "--predictor", "majority",
                               "--out", str(where / "r.json")]),
        "predict": (ov_main, ["predict", str(i["ply"]), "--run", str(i["run"]), "--vocab", "chair,table",
                              "--out", str(where / "p.ply")]),
    }


def _missing_input_cases(i, missing: Path, out: Path):
    return {
        "import": (seg_main, ["import", str(missing), "--out", str(out)]),
        "convert": (seg_main, ["convert", str(missing), str(out / "c.glb")]),
        "inspect": (seg_main, ["inspect", str(missing)]),
        "render": (seg_main, ["render", str(missing), "--out", str(out / "x.png")]),
        "fit": (seg_main, ["fit", "--root", str(missing), "--scene", "s", "--out", str(out / "f.ply")]),
        "build": (seg_main, ["build", "--source", "scannetpp", "--root", str(missing), "--out", str(out)]),
        "split": (seg_main, ["split", "--data", str(missing)]),
        "export-ply": (seg_main, ["export-ply", str(missing), "--scene", "s", "--out", str(out / "e.ply")]),
        "bench": (seg_main, ["bench", "--from-json", str(missing)]),
        "train": (ov_main, ["train", "--data", str(missing), "--out", str(out)]),
        "ov-bench": (ov_main, ["bench", "--data", str(missing), "--predictor", "majority"]),
        "predict": (ov_main, ["predict", str(missing), "--run", str(i["run"]), "--vocab", "a,b",
                              "--out", str(out / "p.ply")]),
    }


def _one_line_error(cli, argv, path_part: str):
    result = CliRunner().invoke(cli, argv)
    assert result.exit_code == 1, (argv, result.output)
    assert "Traceback" not in result.output, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, result.output
    assert path_part in errors[0], errors[0]
    with_json = CliRunner().invoke(cli, argv + ["--json"])
    assert with_json.exit_code == 1, with_json.output
    payload = json.loads(with_json.stdout)
    assert set(payload) == {"error", "path"} and path_part in payload["error"], payload
    assert payload["path"] is not None and path_part in payload["path"], payload
    return errors[0]


COMMANDS_WITH_OUTPUT = ["synth", "import", "convert", "render", "fit", "build", "export-ply", "bench", "train", "ov-bench",
                        "predict"]


@pytest.mark.parametrize("name", COMMANDS_WITH_OUTPUT)
def test_output_under_a_file(inputs, name):
    where = inputs["file"] / "out"
    cli, argv = _cases(inputs, where)[name]
    _one_line_error(cli, argv, str(inputs["file"]))


@pytest.mark.parametrize("name", COMMANDS_WITH_OUTPUT)
def test_read_only_output(inputs, name, tmp_path, monkeypatch):
    ro = _ReadOnly(tmp_path / "ro", monkeypatch)
    try:
        cli, argv = _cases(inputs, ro.path / "out")[name]
        message = _one_line_error(cli, argv, str(ro.path))
        assert "ermission denied" in message
    finally:
        ro.path.chmod(0o755)


@pytest.mark.parametrize("name", ["import", "convert", "inspect", "render", "fit", "build", "split", "export-ply", "bench",
                                  "train", "ov-bench", "predict"])
def test_missing_input(inputs, name, tmp_path):
    missing = tmp_path / "does-not-exist"
    cli, argv = _missing_input_cases(inputs, missing, tmp_path / "out")[name]
    _one_line_error(cli, argv, str(missing))


def test_stress_has_no_paths_but_is_guarded():
    """``seggaussian stress`` takes no path; it is wrapped like every command (its errors are one line)."""
    from cli import seg_stress

    assert seg_stress.command.callback.__wrapped__ is not None


def test_unexpected_error_is_one_line_and_debug_shows_traceback(monkeypatch, tmp_path):
    from cli import seg_inspect

    def boom(path):
        raise TypeError("a bug")

    monkeypatch.setattr("seggaussian.io.inspection.inspect_scene", boom)  # what `inspect` calls for a file
    ply = tmp_path / "x.ply"
    ply.write_bytes(b"ply\n")
    result = CliRunner().invoke(seg_inspect.command, [str(ply)])
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert "internal error (TypeError: a bug)" in result.output
    monkeypatch.setenv("SEGGAUSSIAN_DEBUG", "1")
    result = CliRunner().invoke(seg_inspect.command, [str(ply)])
    assert "Traceback" in result.output


def test_file_size_limit_names_the_file_and_leaves_no_temp(inputs, tmp_path):
    """``ulimit -f`` (what a full disk looks like to a writer): a real subprocess, one line naming the
    file, exit 1, no temporary left."""
    import resource
    import subprocess
    import sys

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024))

    out = tmp_path / "imported"
    proc = subprocess.run([sys.executable, "-m", "cli.seggaussian_cli", "import", str(inputs["ply"]),
                           "--out", str(out)], capture_output=True, text=True, preexec_fn=limit,
                          cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    (line,) = [x for x in proc.stderr.splitlines() if x.startswith("Error:")]
    assert "File too large" in line and str(out) in line, line
    assert [p.name for p in out.iterdir()] == [], list(out.iterdir())
