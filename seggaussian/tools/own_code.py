"""Whether an exception was raised by our own code: the clean-error test of the fuzz and stress classifiers.

A refusal is clean when the innermost frame is inside one of our packages (not inside numpy, plyfile, torch, ...
and not in a caller such as a test). The packages are found by folder, beside this one in a checkout or an
installation, never by a path that merely contains a folder of that name (``tests/seggaussian/``).
"""

from __future__ import annotations

import traceback
from pathlib import Path

#: Packages whose frames count as "our code" when deciding whether an error was raised cleanly.
OWN_PACKAGES = ("seggaussian", "ovgaussian")
#: Their folders: siblings of this package, in a checkout or installed.
OWN_PACKAGE_DIRS = tuple(Path(__file__).resolve().parents[2] / package for package in OWN_PACKAGES)


def raised_by_own_code(exc: BaseException) -> bool:
    """Whether the innermost frame of ``exc``'s traceback lies in one of ``OWN_PACKAGE_DIRS``."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return False
    where = Path(frames[-1].filename).resolve()
    return any(where.is_relative_to(root) for root in OWN_PACKAGE_DIRS)
