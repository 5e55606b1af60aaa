"""The field docs of a config dataclass, read from its source: the one reader (CLI help, config checks).

A config field is documented either by a string right after it (``FitConfig``, ``BenchConfig``, ``TrainConfig``)
or by ``#:`` comment lines right before it (``BuildConfig``); :func:`field_docs` reads both. The CLI's
``config_option`` (``cli/_config_options.py``) takes each option's help from here, so the documentation lives
in one place.
"""

from __future__ import annotations

import ast
import functools
import inspect
import textwrap


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
