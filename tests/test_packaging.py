"""Packaging: the hand-written package list in pyproject.toml covers the tree, and data files ship inside it."""
from __future__ import annotations

from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")

from seggaussian.core.constants import DATA_SPECS_DIR

ROOT = Path(__file__).resolve().parents[1]


def _setuptools_table() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_package_list_names_every_package_folder():
    table = _setuptools_table()
    listed = set(table["packages"])
    on_disk = {
        ".".join(p.parent.relative_to(ROOT).parts)
        for top in ("seggaussian", "ovgaussian", "cli")
        for p in (ROOT / top).rglob("__init__.py")
        if "__pycache__" not in p.parts
    }
    assert on_disk - listed == set(), "packages missing from pyproject.toml [tool.setuptools] packages"
    mapped = set(table.get("package-dir", {}))
    assert listed - on_disk == mapped == {"seggaussian.data_specs"}


def test_data_specs_resolve_through_the_package():
    # The data folder is found through the import system (importlib.resources), and it is the top-level folder
    # of this checkout in an editable install.
    assert DATA_SPECS_DIR.resolve() == (ROOT / "data_specs").resolve()
    for name in ("top100.txt", "vocabularies.json", "replica_to_top100.json"):
        assert (DATA_SPECS_DIR / name).is_file(), name
    package_data = _setuptools_table()["package-data"]["*"]
    shipped = {f"*{p.suffix}" for p in DATA_SPECS_DIR.iterdir() if p.is_file() and p.suffix != ".py"}
    assert shipped <= set(package_data), f"data_specs suffixes not shipped: {shipped - set(package_data)}"
