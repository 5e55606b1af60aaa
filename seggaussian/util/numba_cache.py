"""Where numba keeps its compiled kernels: a folder named by the kernels' source, so an update never runs stale code.

numba's on-disk cache (``cache=True``) checks only the source file of the jitted function itself. A kernel that
calls jitted helpers from another module is inlined with them at compile time, so after an update of the helper
module alone the cached kernel still runs the old helper (seen in this project: the pixel blend weights stopped
equalling the full-view ones after a change elsewhere, until the ``*.nbi`` / ``*.nbc`` files were deleted).

The cache folder is therefore ``<user cache>/seggaussian/numba/<digest>``, where the digest covers the path and
bytes of every module that defines a kernel (``@numba.njit``) in ``seggaussian`` or ``ovgaussian`` and of every
module of its package that it imports, transitively (``seggaussian.util.module_closure``): the helpers it inlines and
the constants it freezes at compile time (``ALPHA_MIN`` from ``seggaussian.core.constants``, ...). Any change to one of
them starts a fresh folder; other changes keep reusing the compiled kernels. Set before numba is imported
(``seggaussian/__init__.py``); a ``NUMBA_CACHE_DIR`` the user exported wins.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from seggaussian.util.module_closure import hash_sources, module_closure

#: The packages whose kernels feed the digest (siblings in the source tree and in an installed wheel).
PACKAGES = ("seggaussian", "ovgaussian")
#: How a module defines a numba kernel in this project: every jitted function is declared with this decorator.
KERNEL_DECORATOR = re.compile(rb"^[ \t]*@numba\.njit\b", re.MULTILINE)
#: Hex digits of the digest in the folder name.
DIGEST_CHARS = 16


def kernel_modules(root: Path) -> tuple[str, ...]:
    """Names of the modules under ``root/<package>`` that define a numba kernel."""
    found = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            if KERNEL_DECORATOR.search(path.read_bytes()):
                parts = path.relative_to(root).with_suffix("").parts
                found.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return tuple(found)


def kernel_source_digest(root: Path) -> str:
    """Digest of the relative path and bytes of every kernel module under ``root`` and of its import closure."""
    closure = sorted({name for entry in kernel_modules(root) for name in module_closure(entry, root)})
    digest = hashlib.sha256()
    hash_sources(digest, closure, root, root)
    return digest.hexdigest()[:DIGEST_CHARS]


def user_cache_root() -> Path:
    """``$XDG_CACHE_HOME`` or ``~/.cache`` (the convention numba's own user-wide cache follows)."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    return Path(xdg) if xdg else Path.home() / ".cache"


def source_root() -> Path:
    """The folder holding the ``seggaussian`` and ``ovgaussian`` packages (the checkout, or site-packages)."""
    return Path(__file__).resolve().parents[2]  # <root>/seggaussian/util/numba_cache.py


def numba_cache_dir(root: Path | None = None) -> Path:
    """The cache folder for the kernels of the source tree (or installation) at ``root``."""
    root = source_root() if root is None else Path(root)
    return user_cache_root() / "seggaussian" / "numba" / kernel_source_digest(root)


def default_numba_cache_dir() -> str | None:
    """The folder to export as ``NUMBA_CACHE_DIR``, created if needed; None when it cannot be used (no home,
    a read-only cache): numba then keeps its own default (``__pycache__`` beside the sources)."""
    try:
        folder = numba_cache_dir()
        folder.mkdir(parents=True, exist_ok=True)
    except (OSError, RuntimeError):  # RuntimeError: Path.home() without HOME or a passwd entry
        return None
    return str(folder) if os.access(folder, os.W_OK) else None
