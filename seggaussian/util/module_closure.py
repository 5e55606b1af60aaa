"""The code a module runs: its package-internal imports, transitively, read from the source with ``ast``.

``module_closure("seggaussian.pipeline.stages.views", root)`` walks the ``import`` statements of the entry module (those
inside functions included, so a lazy import counts as code that runs) and of every module of the same top-level
package they name, with the parent packages (importing ``a.b.c`` runs ``a/__init__.py`` and ``a/b/__init__.py``).
``root`` is the folder that holds the package folder (a checkout or site-packages). Standard library only: the
package's ``__init__`` uses it (numba's cache folder) before anything heavy loads. Users: the build's stage keys
(``seggaussian.pipeline.cache``) and numba's cache folder (``seggaussian.util.numba_cache``), both through
:func:`hash_sources`.
"""

from __future__ import annotations

import ast
import hashlib
from pathlib import Path
from typing import Iterable

#: (path, size, mtime_ns) -> modules the file imports (parsing is the slow part of a closure).
_IMPORTS_MEMO: dict[tuple, frozenset] = {}


def module_file(name: str, root: Path) -> Path | None:
    """The source file of module ``name`` under ``root`` (``.py`` or a package's ``__init__.py``), or None."""
    base = Path(root).joinpath(*name.split("."))
    for path in (base / "__init__.py", base.with_suffix(".py")):
        if path.is_file():
            return path
    return None


def _imports(name: str, path: Path, root: Path) -> frozenset:
    """The modules of ``name``'s own top-level package that ``name`` (file ``path``) imports, with parents."""
    st = path.stat()
    memo_key = (str(path), st.st_size, st.st_mtime_ns, str(root))
    if memo_key in _IMPORTS_MEMO:
        return _IMPORTS_MEMO[memo_key]
    top = name.split(".")[0]
    tree = ast.parse(path.read_bytes(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            # ``from pkg import sub`` imports the submodule ``pkg.sub`` when there is one
            found.update(f"{module}.{alias.name}" for alias in node.names
                         if module_file(f"{module}.{alias.name}", root) is not None)
    ours = {m for m in found if m == top or m.startswith(top + ".")}
    with_parents = {".".join(m.split(".")[:i]) for m in ours for i in range(1, m.count(".") + 2)}
    result = frozenset(m for m in with_parents if module_file(m, root) is not None)
    _IMPORTS_MEMO[memo_key] = result
    return result


def module_closure(entry: str, root: Path) -> tuple[str, ...]:
    """Sorted names of ``entry`` and every module of its top-level package that it imports, transitively."""
    if module_file(entry, root) is None:
        raise ModuleNotFoundError(f"no module {entry} in {root}")
    seen: set[str] = set()
    todo = [entry] + [".".join(entry.split(".")[:i]) for i in range(1, entry.count(".") + 1)]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        todo.extend(_imports(name, module_file(name, root), root) - seen)
    return tuple(sorted(seen))


def hash_sources(digest: "hashlib._Hash", names: Iterable[str], root: Path, relative_to: Path) -> None:
    """Feed ``digest`` the path (relative to ``relative_to``, POSIX) and bytes of each module of ``names`` under
    ``root``, in the given order: the code of a closure, as the build's stage keys and numba's cache folder name it."""
    for name in names:
        path = module_file(name, root)
        if path is None:
            raise ModuleNotFoundError(f"no module {name} in {root}")
        digest.update(path.relative_to(relative_to).as_posix().encode() + b"\0")
        digest.update(path.read_bytes())
