"""Every CLI option that sets a config field has that field's doc as its help, word for word
(``cli._config_options``); the help is never hand-copied beside the config."""

from __future__ import annotations

import dataclasses
import importlib

import click
import pytest

from cli import ovgaussian_cli, seggaussian_cli
from cli._config_options import ConfigOption, config_option
from seggaussian.util.field_docs import field_docs

COMMAND_TARGETS = {**{f"seggaussian {k}": v for k, v in seggaussian_cli.COMMANDS.items()},
                   **{f"ovgaussian {k}": v for k, v in ovgaussian_cli.COMMANDS.items()}}

#: Commands driven by a config dataclass, with the least number of options documented by its fields.
CONFIG_COMMANDS = {"seggaussian fit": 5, "seggaussian build": 16, "seggaussian bench": 3,
                   "ovgaussian train": 18, "ovgaussian bench": 10, "ovgaussian predict": 8}


def _command(name: str) -> click.Command:
    module_name, attribute = COMMAND_TARGETS[name].split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:  # an optional extra (torch) missing
        pytest.skip(f"{name}: {exc}")
    return getattr(module, attribute)


@pytest.mark.parametrize("name", sorted(COMMAND_TARGETS))
def test_config_option_help_is_the_field_doc(name):
    options = [p for p in _command(name).params if isinstance(p, ConfigOption)]
    for option in options:
        fields = {f.name for f in dataclasses.fields(option.config_class)}
        assert option.config_field in fields, (name, option.name)
        assert option.help == field_docs(option.config_class)[option.config_field], (name, option.name)
        assert option.help, (name, option.name)
    assert len(options) >= CONFIG_COMMANDS.get(name, 0), (name, [o.name for o in options])


def test_field_docs_reads_docstrings_and_comment_lines():
    @dataclasses.dataclass(frozen=True)
    class Example:
        after: int = 1
        """Doc after the field,
        wrapped over ``two`` lines."""
        #: Doc in comment lines
        #: before the field.
        before: float = 0.5
        undocumented: bool = False

    docs = field_docs(Example)
    assert docs == {"after": "Doc after the field, wrapped over two lines.",
                    "before": "Doc in comment lines before the field."}
    with pytest.raises(KeyError, match="undocumented"):
        config_option(Example, "undocumented", "--undocumented")
    with pytest.raises(TypeError):
        config_option(Example, "after", "--after", help="a hand-copied help")


def test_comment_documented_config_fields_are_read():
    from seggaussian.pipeline.config import BuildConfig
    from seggaussian.labels.config import TransferConfig

    docs = field_docs(BuildConfig)
    assert docs["root"] == "Raw tree (read only)."
    assert docs["ply_dir"].startswith("Folder of trained PLYs for --source ply")
    assert field_docs(TransferConfig)["max_distance"].startswith("Fixed distance gate in metres")
