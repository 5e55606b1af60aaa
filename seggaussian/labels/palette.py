"""The fixed label palette, colour-by-label painting of Gaussians, and the legend written beside a result.

Palette (fixed, the same in every tool and release): label id ``i >= 0`` gets the colour of HSV
``(frac(i * 0.618033988749895), 0.75, 0.95 if i is even else 0.7)``, rounded to uint8. Golden-ratio
hue steps keep neighbouring ids far apart in hue; alternating value separates ids whose hues come
close again. The same rule serves class ids (index into ``top100.txt`` or into a ``--vocab``) and
instance ids. ``IGNORE_LABEL`` (and any negative id) is ``IGNORE_RGB`` = (128, 128, 128), a neutral
grey no palette colour takes (every palette colour has saturation 0.75).

Colour-by-label: the DC colour of every Gaussian becomes its label colour,
``f_dc = (rgb / 255 - 0.5) / SH_C0``, and the higher SH bands are zeroed (kept in the layout) so the
colour is the same from every side; geometry, opacity and the label properties are unchanged.

Legend: ``<out>.legend.json`` (``{"by", "ignore", "entries": [{"id", "name", "rgb", "count"}]}``, every
id present, sorted by id) and ``<out>.legend.png`` (swatch + name, the ``LEGEND_PNG_ROWS`` most frequent
ids), both written atomically beside the output.
"""

from __future__ import annotations

import colorsys
import os
from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import numpy as np

from seggaussian.util.atomic import atomic_path, write_json_atomic
from seggaussian.core.constants import IGNORE_LABEL, SH_C0
from seggaussian.core.gaussians import Gaussians

__all__ = ["IGNORE_RGB", "GOLDEN_RATIO_CONJUGATE", "label_colours", "palette", "colour_by_labels",
           "LegendEntry", "Legend", "build_legend", "legend_paths", "write_legend"]

#: Hue step between consecutive ids.
GOLDEN_RATIO_CONJUGATE = 0.618033988749895
#: Saturation of every palette colour.
PALETTE_SATURATION = 0.75
#: Value of even / odd ids.
PALETTE_VALUES = (0.95, 0.7)
#: Colour of IGNORE_LABEL (unlabelled Gaussians): neutral grey, DC = 0.
IGNORE_RGB = (128, 128, 128)
#: Rows drawn in the legend PNG (the JSON lists every id).
LEGEND_PNG_ROWS = 40


def _colour_of(label: int) -> tuple[int, int, int]:
    if label < 0 or label == IGNORE_LABEL:
        return IGNORE_RGB
    r, g, b = colorsys.hsv_to_rgb((label * GOLDEN_RATIO_CONJUGATE) % 1.0, PALETTE_SATURATION,
                                  PALETTE_VALUES[label % 2])
    return tuple(int(v) for v in np.round(np.array([r, g, b]) * 255))


def label_colours(labels: np.ndarray) -> np.ndarray:
    """``[N]`` integer label ids -> ``[N, 3]`` uint8 palette colours (``IGNORE_RGB`` for ignore / negative)."""
    labels = np.asarray(labels)
    if labels.dtype.kind not in "iu":
        raise TypeError(f"label ids must be integers, got {labels.dtype}")
    unique, inverse = np.unique(labels.reshape(-1), return_inverse=True)
    table = np.array([_colour_of(int(u)) for u in unique], dtype=np.uint8).reshape(-1, 3)
    return table[inverse].reshape(labels.shape + (3,))


def palette(num_ids: int) -> np.ndarray:
    """``[num_ids, 3]`` uint8 colours of ids ``0 .. num_ids - 1``."""
    return label_colours(np.arange(num_ids, dtype=np.int64))


def colour_by_labels(gaussians: Gaussians, labels: np.ndarray) -> Gaussians:
    """Gaussians whose DC colour is the palette colour of ``labels`` ``[N]``; higher SH bands zeroed."""
    labels = np.asarray(labels)
    if labels.shape != (len(gaussians),):
        raise ValueError(f"labels have shape {labels.shape}, expected ({len(gaussians)},)")
    rgb = label_colours(labels).astype(np.float32) / np.float32(255.0)
    sh = np.zeros_like(gaussians.sh)
    sh[:, 0, :] = (rgb - np.float32(0.5)) / np.float32(SH_C0)
    return Gaussians(gaussians.means, gaussians.quats, gaussians.log_scales, gaussians.opacity_logits, sh,
                     dict(gaussians.extras))


class LegendEntry(NamedTuple):
    """One label of a legend: id, display name, colour (uint8 RGB) and Gaussians carrying it."""

    id: int
    name: str
    rgb: tuple[int, int, int]
    count: int


class Legend(NamedTuple):
    """What a colour-by-label output shows.

    Fields:
        by: the label property coloured by (``semantic`` or ``instance``).
        entries: one per id present, sorted by id (ignore last).
    """

    by: str
    entries: tuple[LegendEntry, ...]

    def to_dict(self) -> dict:
        return {
            "by": self.by,
            "palette": "seggaussian.labels.palette: HSV(frac(id * 0.618034), 0.75, 0.95 | 0.7 for even | odd id)",
            "ignore": {"id": IGNORE_LABEL, "rgb": list(IGNORE_RGB)},
            "entries": [{"id": e.id, "name": e.name, "rgb": list(e.rgb), "count": e.count} for e in self.entries],
        }


def build_legend(labels: np.ndarray, by: str, name_of: Callable[[int], str] | Sequence[str] | None = None) -> Legend:
    """Legend of the ids in ``labels``; ``name_of`` maps an id to a name (a sequence is indexed)."""
    labels = np.asarray(labels).reshape(-1)
    unique, counts = np.unique(labels, return_counts=True)
    order = sorted(range(len(unique)), key=lambda i: (int(unique[i]) == IGNORE_LABEL or int(unique[i]) < 0,
                                                     int(unique[i])))
    entries = []
    for i in order:
        label = int(unique[i])
        if label < 0 or label == IGNORE_LABEL:
            name = "ignore"
        elif name_of is None:
            name = f"{by} {label}"
        elif callable(name_of):
            name = name_of(label)
        else:
            name = name_of[label] if label < len(name_of) else f"{by} {label}"
        entries.append(LegendEntry(label, name, _colour_of(label), int(counts[i])))
    return Legend(by, tuple(entries))


def legend_paths(out: str | os.PathLike) -> tuple[Path, Path]:
    """``(<out>.legend.json, <out>.legend.png)`` beside ``out`` (its last suffix replaced)."""
    out = Path(out)
    stem = out.name[: -len(out.suffix)] if out.suffix else out.name
    return out.with_name(stem + ".legend.json"), out.with_name(stem + ".legend.png")


def legend_image(legend: Legend, rows: int = LEGEND_PNG_ROWS) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB picture: one swatch and name per id (the ``rows`` most frequent ids)."""
    import cv2

    shown = sorted(legend.entries, key=lambda e: -e.count)[:rows]
    shown = sorted(shown, key=lambda e: (e.name == "ignore", e.id))
    row_h, width = 22, 380
    more = len(legend.entries) - len(shown)
    height = row_h * (len(shown) + 1 + (1 if more else 0)) + 6
    image = np.full((height, width, 3), 255, np.uint8)
    cv2.putText(image, f"colour by {legend.by}", (8, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for j, entry in enumerate(shown, start=1):
        y = j * row_h + 4
        image[y: y + row_h - 6, 8: 38] = entry.rgb
        cv2.putText(image, f"{entry.id if entry.name != 'ignore' else '-'}  {entry.name}  ({entry.count})",
                    (46, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if more:
        cv2.putText(image, f"... {more} more in the JSON legend", (8, (len(shown) + 1) * row_h + 16),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return image


def write_legend(out: str | os.PathLike, legend: Legend) -> tuple[Path, Path]:
    """Write the legend JSON and PNG beside ``out``, atomically -> their paths."""
    import cv2

    json_path, png_path = legend_paths(out)
    write_json_atomic(json_path, legend.to_dict())
    with atomic_path(png_path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(legend_image(legend)[..., ::-1])):
            raise OSError(f"{png_path}: could not encode the legend PNG")
    return json_path, png_path
