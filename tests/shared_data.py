"""Where the tests find the shared data (real files written by others; never copied into the repository): the folder
named by the environment variable ``SEGGAUSSIAN_SHARED`` when it is set, else ``../shared`` beside the checkout.
Tests that need a file from it skip with the path they looked at when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

#: The repository root (this file lives in ``tests/``).
REPO = Path(__file__).resolve().parents[1]
#: The shared folder: ``$SEGGAUSSIAN_SHARED`` or ``REPO/../shared``.
SHARED = Path(os.environ["SEGGAUSSIAN_SHARED"]) if os.environ.get("SEGGAUSSIAN_SHARED") else REPO.parent / "shared"
REALDATA = SHARED / "realdata"
WEB_SPLATS = REALDATA / "web_splats"
