"""How every command ends: a one-line summary, or one JSON document with ``--json``; on any error, one line
naming the path and exit status 1 (``guarded``), or ``{"error": ..., "path": ...}`` with ``--json``."""

from __future__ import annotations

import functools
import json
import os
import sys
import traceback
from typing import Callable, NoReturn

import click

from seggaussian.util.jsonsafe import json_safe

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


# --- errors -------------------------------------------------------------------------------------------
#: Set to print the traceback of an unexpected error (a bug) after its one-line message.
DEBUG_ENV = "SEGGAUSSIAN_DEBUG"


def error_path(exc: BaseException) -> str | None:
    """The file or folder an error is about: ``OSError.filename``, an error's ``path`` attribute, or the
    ``PATH: ...`` prefix our error messages start with."""
    if isinstance(exc, OSError) and exc.filename is not None:
        return os.fsdecode(exc.filename)
    path = getattr(exc, "path", None)
    if path is not None:
        return str(path)
    head = str(exc).split(": ", 1)[0]
    if head and head != str(exc) and ("/" in head or os.path.exists(head)) and " " not in head.strip("/"):
        return head
    return None


def error_message(exc: BaseException) -> str:
    """One line: an OS error as ``PATH: reason``; our errors as their message (which names the path)."""
    if isinstance(exc, click.ClickException):
        text = exc.format_message()
    elif isinstance(exc, OSError) and exc.strerror:
        where = error_path(exc)
        text = f"{where}: {exc.strerror}" if where else exc.strerror
        if exc.filename2 is not None:
            text += f" (-> {os.fsdecode(exc.filename2)})"
    elif isinstance(exc, (ValueError, RuntimeError, OSError, LookupError)):
        text = str(exc) or type(exc).__name__
    else:
        text = f"internal error ({type(exc).__name__}: {exc}); set {DEBUG_ENV}=1 for the traceback"
    return " ".join(text.split())


def fail(exc: BaseException, as_json: bool) -> NoReturn:
    """Report ``exc`` as one line on stderr (or ``{"error", "path"}`` on stdout with ``--json``); exit 1."""
    message = error_message(exc)
    if as_json:
        click.echo(to_json({"error": message, "path": error_path(exc)}))
    else:
        click.echo(f"Error: {message}", err=True)
    if os.environ.get(DEBUG_ENV):
        traceback.print_exception(exc)
    sys.exit(1)


def guarded(command: Callable) -> Callable:
    """Decorator of every command's function: any error ends the command with ``fail`` (one line naming
    the path, exit 1, JSON with ``--json``), never a traceback. ``SystemExit`` and ``click.exceptions.Exit``
    pass through; so does ``click.Abort`` (Ctrl-C)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (SystemExit, click.exceptions.Exit, click.Abort, KeyboardInterrupt):
            raise
        except click.UsageError as exc:  # wrong options: click's usage message and exit 2
            if kwargs.get("as_json"):
                fail(exc, True)
            raise
        except Exception as exc:  # noqa: BLE001 -- the one place errors become the command's last line
            fail(exc, bool(kwargs.get("as_json")))

    return wrapper
