"""How every command ends: a one-line summary, or one JSON document with ``--json``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click
import numpy as np

json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of text.")


def _default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def to_json(payload) -> str:
    """JSON text with numpy values converted and NaN written as null."""

    def clean(x):
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(payload), indent=2, default=_default, allow_nan=False)


def finish(summary: str, payload: dict, as_json: bool, details: str | None = None) -> None:
    """Print ``details`` (text mode) then the one-line ``summary``, or the JSON ``payload``."""
    if as_json:
        click.echo(to_json(dict(payload, summary=summary)))
        return
    if details:
        click.echo(details)
    click.echo(summary)
