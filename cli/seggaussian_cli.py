"""``seggaussian``: build labelled 3DGS datasets. Each sub-command lives in its own ``cli/seg_*.py``."""

from __future__ import annotations

import click

from cli._lazy import LazyGroup
from seggaussian import __version__

COMMANDS = {
    "synth": "cli.seg_synth:command",
    "import": "cli.seg_import:command",
    "convert": "cli.seg_convert:command",
    "align": "cli.seg_align:command",
    "inspect": "cli.seg_inspect:command",
    "render": "cli.seg_render:command",
    "fit": "cli.seg_fit:command",
    "build": "cli.seg_build:command",
    "split": "cli.seg_split:command",
    "export-ply": "cli.seg_export_ply:command",
    "bench": "cli.seg_bench:command",
    "stress": "cli.seg_stress:command",
}


@click.group(cls=LazyGroup, lazy_commands=COMMANDS, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="seggaussian")
def main() -> None:
    """SegGaussian: labelled 3D Gaussian Splatting scenes from ScanNet++, Replica, PLY or synthetic rooms."""


if __name__ == "__main__":
    main()
