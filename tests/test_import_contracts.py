"""The layer contracts of ``[tool.importlinter]`` in pyproject.toml hold (``lint-imports``), and they can fail:
a forbidden import written into a temporary copy of the tree breaks the contract it should."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cli", "seggaussian", "ovgaussian")
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def lint_imports(root: Path) -> subprocess.CompletedProcess:
    """``lint-imports`` on the tree at ``root``: its pyproject.toml, its packages first on the path, no cache."""
    assert LINT_IMPORTS.exists(), f"{LINT_IMPORTS} missing: install the test extra (import-linter)"
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run([str(LINT_IMPORTS), "--no-cache", "--no-logo"], cwd=root, env=env,
                          capture_output=True, text=True, timeout=300)


def test_contracts_are_kept():
    run = lint_imports(ROOT)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout and " kept" in run.stdout


@pytest.fixture(scope="module")
def tree_copy(tmp_path_factory) -> Path:
    """The packages and pyproject.toml copied (sources only) into a temporary folder."""
    root = tmp_path_factory.mktemp("tree")
    for package in PACKAGES:
        shutil.copytree(ROOT / package, root / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy2(ROOT / "pyproject.toml", root / "pyproject.toml")
    return root


@pytest.mark.parametrize("module, line, contract", [
    ("seggaussian/core/gaussians.py", "import ovgaussian.metrics",
     "cli is the top layer, and the dataset package never imports the model package"),
    ("seggaussian/render/tiles.py", "import seggaussian.build.cache", "io, core and render never import the build"),
    ("ovgaussian/bench/bootstrap.py", "import ovgaussian.train.schedule",
     "bench, predict and the viewer never import the trainer"),
    ("seggaussian/labels/vote.py", "import seggaussian.build.stages.transfer", "seggaussian in data-flow order"),
])
def test_a_forbidden_import_breaks_its_contract(tree_copy, module, line, contract):
    path = tree_copy / module
    original = path.read_text()
    path.write_text(original + f"\n{line}  # added by the test\n")
    try:
        run = lint_imports(tree_copy)
    finally:
        path.write_text(original)
    assert run.returncode != 0, run.stdout[-2000:]
    broken = run.stdout.split("Broken contracts", 1)[-1]
    assert contract in broken, run.stdout[-4000:]
    assert module.replace("/", ".").removesuffix(".py") in run.stdout


def test_the_copy_itself_is_clean(tree_copy):
    """The mutations above are what breaks the contracts, not the copy."""
    run = lint_imports(tree_copy)
    assert run.returncode == 0, run.stdout[-4000:]
