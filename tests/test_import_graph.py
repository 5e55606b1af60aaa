"""Our own modules are imported at module top (import cycles and layers are import-linter's contracts in
pyproject.toml, tests/test_import_contracts.py; this is what import-linter cannot express).

The graph is built from the source with ``ast``: every ``import`` and ``from ... import`` statement, at module
top, inside ``if``/``try`` and inside functions and methods, resolved to the module it loads
(``from pkg import sub`` is an edge to ``pkg.sub`` when ``sub`` is a module, else to ``pkg``; relative imports
are resolved against the importing module).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("seggaussian", "ovgaussian", "cli")

# Modules allowed to import our own modules inside a function, each with the reason. Keep it short.
FUNCTION_LEVEL_ALLOWED = {
    # Every command module: the CLI lists and helps all commands, so a command imports its library code
    # (torch, numba, open3d behind it) only when it runs; `seggaussian --help` stays fast.
    **{f"cli.{p.stem}": "command body imported on run" for p in (ROOT / "cli").glob("*.py") if p.stem != "__init__"},
}


def module_files(root: Path = ROOT, packages=PACKAGES) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of ``packages`` under ``root``."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _targets(node: ast.Import | ast.ImportFrom, importer: str, is_package: bool, modules: dict) -> list[str]:
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        if node.level:
            base = importer.split(".") if is_package else importer.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            package = ".".join(base + ([node.module] if node.module else []))
        else:
            package = node.module or ""
        names = [f"{package}.{a.name}" if f"{package}.{a.name}" in modules else package for a in node.names]
    return [name for name in names if name in modules]


def import_graph(modules: dict[str, Path]) -> tuple[dict[str, set[str]], list[tuple[str, int, str]]]:
    """(edges ``{importer: {imported}}``, function-level imports ``[(importer, line, imported)]``)."""
    edges: dict[str, set[str]] = {name: set() for name in modules}
    in_functions: list[tuple[str, int, str]] = []

    def visit(node: ast.AST, importer: str, is_package: bool, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                for target in _targets(child, importer, is_package, modules):
                    if target != importer:
                        edges[importer].add(target)
                        if in_function:
                            in_functions.append((importer, child.lineno, target))
            visit(child, importer, is_package,
                  in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    for name, path in modules.items():
        visit(ast.parse(path.read_text(), str(path)), name, path.name == "__init__.py", False)
    return edges, in_functions


def test_finder_sees_every_form_of_import(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg import b\n")
    (pkg / "b.py").write_text("def f():\n    from .sub import c\n")
    (pkg / "sub" / "c.py").write_text("try:\n    import pkg.a as a\nexcept ImportError:\n    pass\n")
    (pkg / "d.py").write_text("from pkg.a import something\nimport os\n")
    modules = module_files(tmp_path, ("pkg",))
    edges, in_functions = import_graph(modules)
    assert edges["pkg.a"] == {"pkg.b"} and edges["pkg.b"] == {"pkg.sub.c"} and edges["pkg.sub.c"] == {"pkg.a"}
    assert edges["pkg.d"] == {"pkg.a"}
    assert in_functions == [("pkg.b", 2, "pkg.sub.c")]


@pytest.fixture(scope="module")
def graph():
    modules = module_files()
    assert {"seggaussian.render.rasterize", "ovgaussian.bench.evaluate", "cli.seg_build"} <= set(modules)
    return import_graph(modules)


def test_own_modules_are_imported_at_module_top(graph):
    _, in_functions = graph
    found = [f"{importer}:{line} imports {target}" for importer, line, target in in_functions
             if importer not in FUNCTION_LEVEL_ALLOWED]
    assert found == [], "function-level imports of our own modules (move them to the top):\n" + "\n".join(found)


def test_allow_list_names_existing_modules():
    assert set(FUNCTION_LEVEL_ALLOWED) <= set(module_files())
