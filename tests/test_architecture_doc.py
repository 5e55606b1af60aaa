"""docs/ARCHITECTURE.md names every module of the packages, and nothing that no longer exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cli", "seggaussian", "ovgaussian", "data_specs", "scripts")


def test_architecture_lists_every_module_once():
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    listed = re.findall(r"^- `([\w/]+\.py)`:", text, flags=re.M)
    modules = sorted(str(p.relative_to(ROOT)) for package in PACKAGES for p in (ROOT / package).rglob("*.py")
                     if "__pycache__" not in p.parts)
    assert len(listed) == len(set(listed))
    assert sorted(set(modules) - set(listed)) == [], "modules missing from docs/ARCHITECTURE.md"
    assert sorted(set(listed) - set(modules)) == [], "docs/ARCHITECTURE.md lists modules that do not exist"
