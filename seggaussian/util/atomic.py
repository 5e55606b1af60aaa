"""Atomic file and folder writes, and the sweep of temporaries left by a killed writer.

Every file and folder the toolkit writes goes through this module:

* ``atomic_path(path)`` yields a temporary name beside ``path``; on success it is renamed onto ``path``,
  on any failure (an exception, a full disk) it is removed. A reader never sees a half-written file.
* The temporary is created with ``os.open(..., 0o666)`` / ``os.mkdir(..., 0o777)``, so the kernel applies
  the user's umask: files end up ``0666 & ~umask`` (0644 under umask 022), folders ``0777 & ~umask``
  (0755), exactly like files written with ``open(path, "w")``. (``tempfile.mkstemp`` would give 0600.)
* Every temporary name has one pattern, ``.<name>.tmp-<pid>-<token><suffix>``; ``is_temp_name``
  recognises it and ``sweep_temps(folder)`` removes those whose writing process is gone. Each command
  sweeps the folders it owns when it starts, so a SIGKILL during a write leaves nothing behind after the
  next run.
* An ``OSError`` raised while writing is re-raised with the *final* path as its ``filename``, so the
  user reads ``File too large: 'dataset/splits.json'`` rather than a temp name or no name at all.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from seggaussian.util.jsonsafe import NAN_AS_NULL, json_safe

#: ``.<name>.tmp-<pid>-<token><suffix>``: the one temp-name pattern of the toolkit (earlier versions
#: wrote ``.<name>.tmp-<pid>``, also recognised).
_TEMP_NAME = re.compile(r"^\..+\.tmp-(\d+)(-[0-9a-f]+)?(\.[A-Za-z0-9]+)?$")
#: Mode of new files and folders before the umask (what ``open(path, "w")`` and ``mkdir`` use).
FILE_MODE = 0o666
DIR_MODE = 0o777


def temp_name(path: Path, suffix: str = "") -> Path:
    """A fresh temporary name beside ``path`` in the toolkit's one pattern."""
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}{suffix}")


def is_temp_name(name: str) -> bool:
    """True for a name made by ``temp_name``."""
    return _TEMP_NAME.match(name) is not None


def _writer_alive(name: str) -> bool:
    """True while the process that made the temp ``name`` still runs (another writer's work in flight)."""
    pid = int(_TEMP_NAME.match(name).group(1))
    if pid == os.getpid():
        return False  # ours: a sweep runs before this process writes anything in that folder
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_temps(folder: str | os.PathLike, *, recursive: bool = False) -> int:
    """Remove the toolkit's temporaries in ``folder`` (and below with ``recursive``) whose writer is gone.

    Returns how many files or folders were removed. A missing folder holds nothing.
    """
    folder = Path(folder)
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return 0
    for entry in entries:
        if is_temp_name(entry.name):
            if _writer_alive(entry.name):
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)
            else:
                Path(entry.path).unlink(missing_ok=True)
            removed += 1
        elif recursive and entry.is_dir(follow_symlinks=False):
            removed += sweep_temps(entry.path, recursive=True)
    return removed


def current_umask() -> int:
    """The process umask, read without changing it where the kernel reports it (Linux), else set-and-restore."""
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def make_dirs(path: str | os.PathLike) -> Path:
    """``mkdir -p`` with the umask-derived mode; an existing non-folder gives ``NotADirectoryError``."""
    path = Path(path)
    path.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
    return path


def ensure_writable_dir(path: str | os.PathLike) -> Path:
    """Create ``path`` (``make_dirs``) and prove it takes a new file, so a command fails on an unusable
    output folder before its long work rather than after. Errors name ``path``."""
    path = Path(path)
    try:
        make_dirs(path)
        probe = temp_name(path / "probe")
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE))
        os.unlink(probe)
    except OSError as exc:
        raise _named(exc, path) from None
    return path


def _named(exc: OSError, path: Path) -> OSError:
    """``exc`` re-made to name ``path`` (the final file, never the temporary)."""
    if exc.errno is None:
        return exc
    named = type(exc)(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))
    named.__cause__ = exc
    return named


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield an empty temporary file beside ``path``; renamed onto ``path`` on success, removed on failure.

    The temporary already exists with the umask-derived mode; open it for writing (``"wb"`` keeps the
    mode). ``suffix`` lets writers that infer the format from the name (``cv2.imwrite``) see it.
    A caller that decides to keep the existing file removes the temporary; nothing is renamed then.
    """
    path = Path(path)
    try:
        make_dirs(path.parent)
        tmp = temp_name(path, suffix)
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, FILE_MODE))
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        yield tmp
        if os.path.lexists(tmp):
            os.chmod(tmp, FILE_MODE & ~current_umask())  # writers that re-create the file (safetensors: 0600)
            os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise _named(exc, path) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``path``; on success it replaces ``path`` (an existing
    folder is moved aside under a temp name, then removed), on failure it is removed."""
    path = Path(path)
    try:
        make_dirs(path.parent)
        tmp = temp_name(path)
        os.mkdir(tmp, DIR_MODE)
    except OSError as exc:
        raise _named(exc, path) from None
    try:
        yield tmp
        old = None
        if path.exists():
            old = temp_name(path)
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise _named(exc, path) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def remove_dir_atomic(path: str | os.PathLike) -> bool:
    """Remove the folder ``path`` as one step: it is renamed to a temporary name (gone from ``path`` at once,
    never half-deleted there), then deleted; a kill during the deletion leaves only that temporary, which
    ``sweep_temps`` removes. Returns False when ``path`` did not exist."""
    path = Path(path)
    doomed = temp_name(path)
    try:
        os.replace(path, doomed)
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise _named(exc, path) from None
    shutil.rmtree(doomed, ignore_errors=True)
    return True


def write_bytes_atomic(path: str | os.PathLike, data: bytes, *, only_if_changed: bool = False) -> bool:
    """``data`` to ``path``, atomically and fsynced. With ``only_if_changed``, a file that already holds
    exactly these bytes is left alone (mtime kept) and False is returned."""
    path = Path(path)
    if only_if_changed and path.is_file() and path.stat().st_size == len(data) and path.read_bytes() == data:
        return False
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    return True


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """``text`` (UTF-8) to ``path``, atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def json_text(payload, *, sort_keys: bool = False, nan: str = NAN_AS_NULL) -> str:
    """Indented JSON (numpy values converted; NaN/Inf by the policy ``nan``, see jsonsafe) with a final newline."""
    return json.dumps(json_safe(payload, nan), indent=2, sort_keys=sort_keys, allow_nan=False) + "\n"


def write_json_atomic(path: str | os.PathLike, payload, *, nan: str = NAN_AS_NULL, sort_keys: bool = False,
                      only_if_changed: bool = False) -> bool:
    """``payload`` as indented JSON to ``path``, atomically (see ``write_bytes_atomic``).

    ``nan``: NAN_AS_NULL (NaN/Inf written as null) or NAN_IS_ERROR (ValueError, nothing written). The one
    JSON-file writer of the tree: other modules call it with their policy rather than keeping a copy."""
    text = json_text(payload, sort_keys=sort_keys, nan=nan)  # raises before anything is written
    return write_bytes_atomic(path, text.encode(), only_if_changed=only_if_changed)
