"""``seggaussian split``: train / val / xval assignment and split-named shards of a built dataset."""

from __future__ import annotations

from pathlib import Path

import click

from cli._output import finish, guarded, json_option


def _ratios(ctx, param, value: str) -> tuple[int, int, int]:
    try:
        parts = tuple(int(v) for v in value.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 3 or min(parts) < 0 or parts[0] + parts[1] == 0:
        raise click.BadParameter(f"expected three non-negative integers TRAIN,VAL,XVAL, got {value!r}")
    return parts


@click.command("split")
@click.option("--data", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Dataset folder written by `seggaussian build`.")
@click.option("--ratios", default="230,50,8", show_default=True, callback=_ratios,
              help="train,val,xval. ScanNet++ scenes split train:val; every Replica scene is xval.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the stable hash order.")
@click.option("--reassign", is_flag=True, help="Recompute every assignment (default: existing scenes never move).")
@json_option
@guarded
def command(data: Path, ratios, seed: int, reassign: bool, as_json: bool) -> None:
    """Assign scenes to train / val / xval and write splits.json and the split-named shards."""
    from seggaussian.pipeline.assembly import split_dataset
    from seggaussian.pipeline.config import SplitConfig

    counts, reasons, rewritten = split_dataset(data, SplitConfig(ratios=ratios, seed=seed, reassign=reassign))
    by_reason: dict[str, int] = {}
    for r in reasons.values():
        by_reason[r] = by_reason.get(r, 0) + 1
    summary = (f"{data}: {counts['train']} train / {counts['val']} val / {counts['xval']} xval scenes "
               f"({', '.join(f'{n} {r}' for r, n in sorted(by_reason.items()))}); "
               f"{'shards reassembled' if rewritten else 'shards unchanged'}")
    finish(summary, {"dataset": str(data), "counts": counts, "reasons": reasons, "rewritten": rewritten}, as_json)
