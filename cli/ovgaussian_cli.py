"""``ovgaussian``: train, benchmark and query the open-vocabulary model. One module per sub-command."""

from __future__ import annotations

import click

from cli._lazy import LazyGroup
from ovgaussian import __version__

COMMANDS = {
    "train": "cli.ov_train:command",
    "bench": "cli.ov_bench:command",
    "bench-suite": "cli.ov_bench_suite:command",
    "predict": "cli.ov_predict:command",
    "view": "cli.ov_view:command",
}


@click.group(cls=LazyGroup, lazy_commands=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ovgaussian")
def main() -> None:
    """OVGaussian: generalizable open-vocabulary segmentation of 3D Gaussian scenes."""


if __name__ == "__main__":
    main()
