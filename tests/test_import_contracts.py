"""The layer contracts of ``[tool.importlinter]`` in pyproject.toml hold (``lint-imports``), and they can fail:
a forbidden import written into a temporary copy of the tree breaks the contract it should."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

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


#: (module, line added to it, the contract that line breaks)
MUTATIONS = (
    ("seggaussian/core/gaussians.py", "import ovgaussian.metrics",
     "cli is the top layer, and the dataset package never imports the model package"),
    ("seggaussian/render/tiles.py", "import seggaussian.pipeline.cache", "io, core and render never import the pipeline"),
    ("ovgaussian/bench/bootstrap.py", "import ovgaussian.train.schedule",
     "bench, predict and the viewer never import the trainer"),
    ("seggaussian/labels/vote.py", "import seggaussian.pipeline.stages.transfer", "seggaussian in data-flow order"),
)


def test_forbidden_imports_break_their_contracts(tmp_path):
    """One copy of the tree with four forbidden imports added: each breaks its contract (one lint-imports run)."""
    for package in PACKAGES:
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy2(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    for module, line, _ in MUTATIONS:
        path = tmp_path / module
        path.write_text(path.read_text() + f"\n{line}  # added by the test\n")
    run = lint_imports(tmp_path)
    assert run.returncode != 0, run.stdout[-2000:]
    broken = run.stdout.split("Broken contracts", 1)[-1]
    for module, line, contract in MUTATIONS:
        assert contract in broken, f"{line} in {module} did not break {contract!r}:\n" + run.stdout[-4000:]
        assert module.replace("/", ".").removesuffix(".py") in broken, run.stdout[-4000:]
