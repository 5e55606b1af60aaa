"""No tracked file names this machine's checkout or shared folder by an absolute path: shared data is found at
``../shared`` beside the checkout or through ``$SEGGAUSSIAN_SHARED`` (tests/shared_data.py), and benchmark
commands are written relative to the repository root."""

from __future__ import annotations

import subprocess

from shared_data import REPO, SHARED


def machine_paths() -> list[str]:
    """The absolute spellings of the checkout and the shared folder on this machine (resolved and as given)."""
    paths = {str(REPO), str(REPO.resolve()), str(SHARED.absolute()), str(SHARED.resolve())}
    return sorted(p for p in paths if len(p) > 1)


def test_no_tracked_file_holds_a_machine_path():
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    needles = [p.encode() for p in machine_paths()]
    found = []
    for name in filter(None, files):
        path = REPO / name.decode()
        if not path.is_file():
            continue
        data = path.read_bytes()
        found += [f"{name.decode()}: {needle.decode()}" for needle in needles if needle in data]
    assert len(files) > 100  # the whole tree was read
    assert found == [], "absolute machine paths in tracked files:\n" + "\n".join(found)
