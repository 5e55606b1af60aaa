"""Build cache keys: what each stage's outputs depend on, hashed; and the per-stage cache record.

A stage key is sha256 of (the scene's input fingerprint, the upstream stage's key, the stage's settings, the
digest of the stage's code). The code digest is taken from the source: every module of the seggaussian
package that the stage's entry module imports, transitively (``seggaussian.util.module_closure``: a walk of the
``import`` statements with ``ast``, those inside functions included, so a lazy import counts as code the stage runs),
plus the data files of ``data_specs/`` when the closure holds ``seggaussian.core.constants`` (the one module that
reads them). A change anywhere in a stage's code therefore invalidates that stage and those downstream of it,
and no other; there is no version number to bump by hand.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import seggaussian
from seggaussian.util import module_closure as module_closure_mod
from seggaussian.util.atomic import write_json_atomic
from seggaussian.core.constants import DATA_SPECS_DIR

PACKAGE = "seggaussian"
#: The package's source folder; the code digests read the modules from here.
PACKAGE_DIR = Path(seggaussian.__file__).resolve().parent
#: The module that reads ``data_specs/``: a closure holding it depends on the data files too.
DATA_SPECS_READER = "seggaussian.core.constants"
#: The suffixes of data_specs/ files that code reads (prose, the package marker and bytecode stay out of the key).
DATA_SUFFIXES = (".txt", ".json", ".csv")


def sha256_json(payload) -> str:
    """sha256 of the canonical JSON of ``payload`` (sorted keys; non-JSON values by ``str``)."""
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


def module_closure(entry: str, package_dir: Path | None = None) -> tuple[str, ...]:
    """Sorted names of ``entry`` and every seggaussian module it imports, transitively
    (``seggaussian.util.module_closure``; ``package_dir`` is the package folder, by default this installation's)."""
    try:
        return module_closure_mod.module_closure(entry, (package_dir or PACKAGE_DIR).parent)
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError(f"build cache: {error}") from None


def data_specs_hash() -> str:
    """sha256 of the data files readers use (class lists, mappings) in ``data_specs/`` (prose and code excluded)."""
    h = hashlib.sha256()
    if DATA_SPECS_DIR.is_dir():
        for f in sorted(p for p in DATA_SPECS_DIR.rglob("*") if p.is_file() and p.suffix in DATA_SUFFIXES):
            h.update(str(f.relative_to(DATA_SPECS_DIR)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def code_digest(entry: str) -> str:
    """sha256 of the source of ``module_closure(entry)`` (relative path and bytes of each file), plus the
    data_specs data files when the closure reads them."""
    h = hashlib.sha256()
    closure = module_closure(entry)
    module_closure_mod.hash_sources(h, closure, PACKAGE_DIR.parent, PACKAGE_DIR)
    if DATA_SPECS_READER in closure:
        h.update(data_specs_hash().encode())
    return h.hexdigest()


class StageRecord:
    """Cache record of one stage of one scene (``<scene dir>/<stage>.json``)."""

    def __init__(self, scene_dir: Path, name: str):
        self.path = scene_dir / f"{name}.json"
        self.dir = scene_dir

    def cached(self, key: str, outputs) -> dict | None:
        """The record when it holds ``key`` and every output file exists, else None (the stage must run)."""
        if not self.path.is_file():
            return None
        try:
            record = json.loads(self.path.read_text())
        except json.JSONDecodeError:
            return None
        if record.get("key") != key or not all((self.dir / o).is_file() for o in outputs):
            return None
        return record

    def save(self, key: str, info: dict, parts=None) -> None:
        """Record the stage as done; ``parts`` (what the key was made of) only helps explain cache misses."""
        write_json_atomic(self.path, {"key": key, "info": info, "key_parts": json.loads(json.dumps(parts, default=str))},
                          sort_keys=True, only_if_changed=True)
