"""CLI options whose help is the field doc of a config dataclass (one copy of each sentence).

A config field is documented either by a string right after it (``FitConfig``, ``BenchConfig``, ``TrainConfig``)
or by ``#:`` comment lines right before it (``BuildConfig``); ``field_docs`` reads both. ``config_option`` is
``click.option`` with ``help`` taken from ``field_docs(config)[field]``; the option remembers its field, so
``tests/test_cli_help.py`` checks every such option of every command against the config it names.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap

import click


@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """``{field name: doc}`` of a config dataclass: the string after each field, else the ``#:`` comment lines
    before it; whitespace collapsed, reStructuredText ``literals`` unquoted (CLI help)."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    body = ast.parse(source).body[0].body
    docs: dict[str, str] = {}
    for index, node in enumerate(body):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        following = body[index + 1] if index + 1 < len(body) else None
        if (isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)):
            text = following.value.value
        else:
            comments = []
            row = node.lineno - 2  # the line above the field (lineno is 1-based)
            while row >= 0 and lines[row].strip().startswith("#:"):
                comments.insert(0, lines[row].strip()[2:])
                row -= 1
            if not comments:
                continue
            text = " ".join(comments)
        docs[node.target.id] = " ".join(text.split()).replace("``", "")
    return docs


class ConfigOption(click.Option):
    """A ``click.Option`` documented by one field of a config dataclass."""

    def __init__(self, *args, config_class: type, config_field: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.config_class = config_class
        self.config_field = config_field


def config_option(config_class: type, config_field: str, *param_decls: str, **kwargs):
    """``click.option(*param_decls, **kwargs)`` whose help is the doc of ``config_class.config_field``."""
    docs = field_docs(config_class)
    if config_field not in docs:
        raise KeyError(f"{config_class.__name__}.{config_field} has no field doc")
    if "help" in kwargs:
        raise TypeError("config_option takes its help from the field doc; do not pass help=")
    return click.option(*param_decls, cls=ConfigOption, help=docs[config_field], config_class=config_class,
                        config_field=config_field, **kwargs)
