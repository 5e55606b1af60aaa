"""CLI options whose help is the field doc of a config dataclass (one copy of each sentence).

A config field is documented either by a string right after it (``FitConfig``, ``BenchConfig``, ``TrainConfig``)
or by ``#:`` comment lines right before it (``BuildConfig``); ``seggaussian.util.field_docs`` reads both.
``config_option`` is ``click.option`` with ``help`` taken from ``field_docs(config)[field]``; the option remembers
its field, so
``tests/cli/test_cli_help.py`` checks every such option of every command against the config it names.
"""

from __future__ import annotations

import click

from seggaussian.util.field_docs import field_docs


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


def transform_options(function):
    """``--transform FILE|SPEC`` and ``--from-frame AXES`` (``FrameConfig``): the splat's frame, moved into the
    scene's on reading."""
    from seggaussian.frames.frame_config import FrameConfig

    function = config_option(FrameConfig, "from_frame", "--from-frame", default=None, metavar="AXES")(function)
    return config_option(FrameConfig, "transform", "--transform", default=None, metavar="FILE|SPEC")(function)
