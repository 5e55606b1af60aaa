"""Arrow tables of one scene: Gaussians and views to ``gaussians`` / ``views`` rows and back.

Schemas in ``seggaussian/shards/schema.py``; images are encoded and decoded by ``seggaussian.shards.images``.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from seggaussian.core.cameras import Camera
from seggaussian.core.constants import IGNORE_LABEL
from seggaussian.core.gaussians import Gaussians
from seggaussian.shards.images import decode_label_map, decode_rgb, image_format
from seggaussian.shards.layout import ShardError
from seggaussian.shards.records import ViewCamera, ViewRecord, ViewRow
from seggaussian.shards.schema import GAUSSIANS_SCHEMA, VIEWS_SCHEMA


def _fixed_list(values: np.ndarray, width: int, dtype) -> pa.FixedSizeListArray:
    flat = pa.array(np.ascontiguousarray(values, dtype=dtype).reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, width)


def gaussians_table(scene_id: str, gaussians: Gaussians) -> pa.Table:
    """The ``gaussians`` rows of one scene. ``gaussians.extras`` must hold semantic, instance,
    transfer_distance and (optionally) multilabel."""
    n = len(gaussians)
    ex = gaussians.extras
    for key in ("semantic", "instance", "transfer_distance"):
        if key not in ex:
            raise ValueError(f"scene {scene_id}: Gaussians.extras lacks {key!r}")
    multilabel = ex.get("multilabel")
    if multilabel is None:
        multilabel = np.full((n, 3), IGNORE_LABEL, np.int32)
        multilabel[:, 0] = ex["semantic"]
    k = gaussians.num_sh_coeffs
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * (k * 3))
    sh = pa.ListArray.from_arrays(offsets, pa.array(np.ascontiguousarray(gaussians.sh).reshape(-1)))
    distance = np.asarray(ex["transfer_distance"], np.float32)
    if not np.isfinite(distance).all():
        raise ValueError(f"scene {scene_id}: transfer_distance holds NaN/Inf")
    columns = [
        pa.repeat(pa.scalar(scene_id, pa.string()), n),
        _fixed_list(gaussians.means, 3, np.float32),
        _fixed_list(gaussians.quats, 4, np.float32),
        _fixed_list(gaussians.log_scales, 3, np.float32),
        pa.array(gaussians.opacity_logits.astype(np.float32)),
        pa.array(np.full(n, gaussians.sh_degree, np.uint8)),
        sh,
        pa.array(np.asarray(ex["semantic"], np.int32)),
        pa.array(np.asarray(ex["instance"], np.int32)),
        _fixed_list(multilabel, 3, np.int32),
        pa.array(distance),
    ]
    return pa.Table.from_arrays(columns, schema=GAUSSIANS_SCHEMA)


def views_table(scene_id: str, rows: list) -> pa.Table:
    """The ``views`` rows of one scene (``rows``: ViewRow list, stored in the given order)."""
    n = len(rows)
    columns = [
        pa.array([scene_id] * n, pa.string()),
        pa.array([r.name for r in rows], pa.string()),
        pa.array([r.role for r in rows], pa.string()),
        pa.array([r.camera.width for r in rows], pa.int32()),
        pa.array([r.camera.height for r in rows], pa.int32()),
        _fixed_list(np.array([r.camera.K for r in rows]).reshape(n, 9), 9, np.float64),
        _fixed_list(np.array([r.camera.viewmat for r in rows]).reshape(n, 16), 16, np.float64),
        pa.array([r.rgb for r in rows], pa.binary()),
        pa.array([image_format(r.rgb) for r in rows], pa.string()),
        pa.array([r.semantic for r in rows], pa.binary()),
        pa.array([r.instance for r in rows], pa.binary()),
        pa.array([float(r.label_coverage) for r in rows], pa.float32()),
    ]
    return pa.Table.from_arrays(columns, schema=VIEWS_SCHEMA)


def _flat(table: pa.Table, column: str, width: int, dtype) -> np.ndarray:
    arr = table.column(column).combine_chunks()
    return np.asarray(arr.flatten().to_numpy(zero_copy_only=False), dtype=dtype).reshape(-1, width)


def table_to_gaussians(table: pa.Table) -> Gaussians:
    """``gaussians`` rows of one scene -> Gaussians with extras semantic, instance, multilabel, transfer_distance."""
    n = table.num_rows
    if n == 0:
        g = Gaussians.empty()
        z = np.zeros(0, np.int32)
        return g.with_extras(semantic=z, instance=z.copy(), multilabel=np.zeros((0, 3), np.int32),
                             transfer_distance=np.zeros(0, np.float32))
    degrees = np.unique(table.column("sh_degree").to_numpy())
    if len(degrees) != 1:
        raise ShardError(f"scene {table.column('scene_id')[0]}: mixed SH degrees {degrees.tolist()}")
    k = (int(degrees[0]) + 1) ** 2
    sh = np.asarray(table.column("sh").combine_chunks().flatten().to_numpy(), np.float32).reshape(n, k, 3)
    return Gaussians(
        _flat(table, "means", 3, np.float32),
        _flat(table, "quats", 4, np.float32),
        _flat(table, "log_scales", 3, np.float32),
        np.asarray(table.column("opacity_logit").to_numpy(), np.float32),
        sh,
        {
            "semantic": np.asarray(table.column("semantic").to_numpy(), np.int32),
            "instance": np.asarray(table.column("instance").to_numpy(), np.int32),
            "multilabel": _flat(table, "multilabel", 3, np.int32),
            "transfer_distance": np.asarray(table.column("transfer_distance").to_numpy(), np.float32),
        },
    )


def table_to_cameras(table: pa.Table) -> list[ViewCamera]:
    """``views`` rows of one scene (the camera columns suffice) -> their cameras (stored order)."""
    cols = table.select(["view_name", "role", "K", "viewmat", "width", "height"]).to_pydict()
    return [ViewCamera(cols["view_name"][i], cols["role"][i],
                       Camera(np.array(cols["K"][i]).reshape(3, 3), np.array(cols["viewmat"][i]).reshape(4, 4),
                              cols["width"][i], cols["height"][i]))
            for i in range(table.num_rows)]


def table_to_views(table: pa.Table) -> list[ViewRecord]:
    """``views`` rows of one scene -> decoded ViewRecords (stored order)."""
    out = []
    cols = table.to_pydict()
    for i in range(table.num_rows):
        what = f"view {cols['scene_id'][i]}/{cols['view_name'][i]}"
        camera = Camera(np.array(cols["K"][i]).reshape(3, 3), np.array(cols["viewmat"][i]).reshape(4, 4),
                        cols["width"][i], cols["height"][i])
        out.append(ViewRecord(
            cols["view_name"][i], cols["role"][i], camera,
            decode_rgb(cols["rgb"][i], what + " rgb"),
            decode_label_map(cols["semantic"][i], what + " semantic"),
            decode_label_map(cols["instance"][i], what + " instance"),
        ))
    return out
