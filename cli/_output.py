"""How every command ends: a one-line summary, or one JSON document with ``--json``."""

from __future__ import annotations

import json

import click

from seggaussian.jsonsafe import json_safe

json_option = click.option("--json", "as_json", is_flag=True, help="Print one JSON document instead of text.")


def to_json(payload) -> str:
    """JSON text with numpy values converted and NaN written as null."""
    return json.dumps(json_safe(payload), indent=2, allow_nan=False)


def finish(summary: str, payload: dict, as_json: bool, details: str | None = None) -> None:
    """Print ``details`` (text mode) then the one-line ``summary``, or the JSON ``payload``."""
    if as_json:
        click.echo(to_json(dict(payload, summary=summary)))
        return
    if details:
        click.echo(details)
    click.echo(summary)
