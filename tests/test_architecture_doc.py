"""docs/ARCHITECTURE.md names every module of the packages, and nothing that no longer exists; its data-flow
picture names every package folder and nothing else ending in ``/``; no module is over 500 lines unless the
page's exceptions list it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cli", "seggaussian", "ovgaussian", "data_specs", "scripts")
#: Package folders the picture must name (besides these top folders, every folder with an ``__init__.py`` below
#: the two library packages).
PICTURE_ROOTS = ("cli", "seggaussian", "ovgaussian")
#: Folders a bare name in the picture (``fit/``, ``io/ply/``) is looked up in, besides the repository root.
PICTURE_BASES = ("seggaussian", "ovgaussian")
#: A package reference in the picture: words joined by ``/`` and ending in ``/`` (``fit/``, ``io/ply/``,
#: ``seggaussian/``), not part of a longer path or file name.
PACKAGE_REFERENCE = re.compile(r"(?<![\w./<>-])((?:[A-Za-z_][\w-]*/)+)")
MAX_LINES = 500
EXCEPTIONS_HEADING = "## Exceptions to the 500-line rule"


def architecture() -> str:
    return (ROOT / "docs" / "ARCHITECTURE.md").read_text()


def module_paths() -> list[str]:
    return sorted(str(p.relative_to(ROOT)) for package in PACKAGES for p in (ROOT / package).rglob("*.py")
                  if "__pycache__" not in p.parts)


def picture(text: str) -> str:
    """The data-flow picture: the first fenced block, which must come before the first section."""
    match = re.search(r"^```[^\n]*\n(.*?)^```$", text, flags=re.M | re.S)
    assert match, "docs/ARCHITECTURE.md has no fenced data-flow picture"
    first_section = re.search(r"^## ", text, flags=re.M)
    assert first_section is None or match.start() < first_section.start(), "the picture must lead the page"
    return match.group(1)


def package_folders() -> set[Path]:
    """Every package folder the picture must name: the top folders and every package below the libraries."""
    found = {ROOT / name for name in PICTURE_ROOTS}
    for base in PICTURE_BASES:
        found |= {p.parent for p in (ROOT / base).rglob("__init__.py") if "__pycache__" not in p.parts}
    return found


def resolve(reference: str) -> list[Path]:
    """The package folders a picture reference can mean: under the root, or under either library package."""
    name = reference.rstrip("/")
    candidates = [ROOT / name] + [ROOT / base / name for base in PICTURE_BASES]
    return sorted({p for p in candidates if (p / "__init__.py").is_file()})


def exceptions(text: str) -> dict[str, str]:
    """``{module path: its line}`` of the exceptions section (``- `path.py` (...): reason``)."""
    start = text.index(EXCEPTIONS_HEADING)
    end = text.find("\n## ", start + 1)
    section = text[start: end if end >= 0 else len(text)]
    return {m.group(1): m.group(0) for m in re.finditer(r"^- `([\w/]+\.py)`[^\n]*", section, flags=re.M)}


def line_count(path: Path) -> int:
    return len(path.read_text().splitlines())


def test_architecture_lists_every_module_once():
    text = architecture()
    listed = re.findall(r"^- `([\w/]+\.py)`:", text, flags=re.M)
    modules = module_paths()
    assert len(listed) == len(set(listed))
    assert sorted(set(modules) - set(listed)) == [], "modules missing from docs/ARCHITECTURE.md"
    assert sorted(set(listed) - set(modules)) == [], "docs/ARCHITECTURE.md lists modules that do not exist"


def test_picture_names_every_package_and_only_packages():
    references = PACKAGE_REFERENCE.findall(picture(architecture()))
    assert references, "the picture names no package"
    named: set[Path] = set()
    for reference in references:
        folders = resolve(reference)
        assert len(folders) == 1, (f"the picture's {reference!r} is not exactly one package folder "
                                   f"(candidates: {[str(f.relative_to(ROOT)) for f in folders]})")
        named |= set(folders)
    missing = sorted(str(p.relative_to(ROOT)) + "/" for p in package_folders() - named)
    assert missing == [], "package folders missing from the picture of docs/ARCHITECTURE.md"


def test_picture_rule_catches_a_wrong_name():
    assert PACKAGE_REFERENCE.findall("io/ply/ + fit/ and labels/oracle.py, not <scene>.transform.json or "
                                     "metrics.jsonl or seggaussian/render/") == [
        "io/ply/", "fit/", "labels/", "seggaussian/render/"]
    assert resolve("io/ply/") == [ROOT / "seggaussian" / "io" / "ply"]
    assert resolve("cli/") == [ROOT / "cli"]
    assert resolve("nonexistent/") == []


def test_no_module_over_500_lines_unless_listed():
    listed = exceptions(architecture())
    long = {path: line_count(ROOT / path) for path in module_paths() if line_count(ROOT / path) > MAX_LINES}
    unlisted = {path: n for path, n in long.items() if path not in listed}
    assert unlisted == {}, (f"modules over {MAX_LINES} lines: split them (one idea each) or list them with their "
                            f"reason under '{EXCEPTIONS_HEADING}' in docs/ARCHITECTURE.md")
    stale = sorted(path for path in listed if path not in long)
    assert stale == [], f"listed as over {MAX_LINES} lines but not (any more): remove them from the exceptions"


def _import_free_packages() -> list[Path]:
    """Package folders whose ``__init__`` imports nothing: their ``__all__`` names their public modules."""
    found = []
    for init in sorted((ROOT / "seggaussian").rglob("__init__.py")) + sorted((ROOT / "ovgaussian").rglob("__init__.py")):
        tree = ast.parse(init.read_text())
        if not any(isinstance(n, (ast.Import, ast.ImportFrom)) for n in ast.walk(tree)):
            found.append(init.parent)
    return found


def test_all_of_import_free_packages_names_their_public_modules():
    packages = _import_free_packages()
    assert len(packages) >= 15  # the subpackages of the restructure
    for package in packages:
        tree = ast.parse((package / "__init__.py").read_text())
        declared = next((ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                         and any(getattr(t, "id", None) == "__all__" for t in n.targets)), None)
        public = sorted([p.stem for p in package.glob("*.py") if not p.stem.startswith("_")]
                        + [p.name for p in package.iterdir() if (p / "__init__.py").is_file()])
        assert declared is not None and sorted(declared) == public, (str(package.relative_to(ROOT)), declared, public)
