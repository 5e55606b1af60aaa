"""The dataset package never depends on the model package: no module of ``seggaussian`` imports ``ovgaussian``,
at module top or inside a function, by statement or by ``importlib``."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import seggaussian

PACKAGE = Path(seggaussian.__file__).resolve().parent
FORBIDDEN = "ovgaussian"


def forbidden_imports(source: str, filename: str) -> list[str]:
    """``file:line: what`` for every import of FORBIDDEN in ``source`` (any nesting)."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            called = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if called in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                names = [node.args[0].value]
        found += [f"{filename}:{node.lineno}: imports {n}" for n in names
                  if n == FORBIDDEN or n.startswith(FORBIDDEN + ".")]
    return found


def test_checker_sees_every_import_form():
    source = ("import ovgaussian.train.losses\n"
              "def f():\n    from ovgaussian import model\n"
              "def g():\n    importlib.import_module('ovgaussian.data.training_data')\n"
              "import ovgaussianx\nfrom seggaussian import ovgaussian_like\n")
    assert [line.split(": ", 1)[0] for line in forbidden_imports(source, "x.py")] == ["x.py:1", "x.py:3", "x.py:5"]


def test_seggaussian_never_imports_ovgaussian():
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 30  # the whole package was scanned
    found = [hit for f in files for hit in forbidden_imports(f.read_text(), str(f.relative_to(PACKAGE.parent)))]
    assert found == [], "the dataset package imports the model package:\n" + "\n".join(found)


def test_importing_the_tools_loads_no_model_module():
    code = ("import sys, seggaussian.tools.sweep.run, seggaussian.tools.stress, seggaussian.sources.layout\n"
            "bad = sorted(m for m in sys.modules if m == 'ovgaussian' or m.startswith('ovgaussian.'))\n"
            "assert not bad, bad\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
