"""The parts of a COLMAP sparse model a frame computation needs: image poses (world-to-camera) and 3D points.

Reads the text (``images.txt``, ``points3D.txt``) and the binary (``images.bin``, ``points3D.bin``) formats of
COLMAP's ``Reconstruction::Read{Images,Points3D}{Text,Binary}``; ``cameras.*`` is not needed (intrinsics do not
enter a frame) and not read. Binary layouts (little-endian):

- ``images.bin``: ``uint64 n``; per image ``int32 id, 4 x float64 qvec (w, x, y, z), 3 x float64 tvec,
  int32 camera_id``, the name as bytes up to a NUL, ``uint64 num_points2D``, then ``num_points2D x
  (float64 x, float64 y, int64 point3D_id)``.
- ``points3D.bin``: ``uint64 n``; per point ``uint64 id, 3 x float64 xyz, 3 x uint8 rgb, float64 error,
  uint64 track_length``, then ``track_length x (int32 image_id, int32 point2D_idx)``.

A model folder is one holding ``images`` and ``points3D`` files; binary is preferred when both exist (as COLMAP
does). ``find_colmap_model`` also accepts a dataset folder with ``sparse/0/`` or ``sparse/`` (gsplat's layout).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from seggaussian.core.rotations import quats_to_rotmats

#: A COLMAP quaternion whose norm is below this cannot be normalized (rotation undefined).
COLMAP_QUAT_NORM_EPS = 1e-12
_IMAGE_HEAD = struct.Struct("<i4d3di")
_POINT2D = 24  # bytes: float64 x, float64 y, int64 point3D_id
_POINT_HEAD = struct.Struct("<Q3d3Bd")
_TRACK_ELEMENT = 8  # bytes: int32 image_id, int32 point2D_idx
_U64 = struct.Struct("<Q")


class ColmapModelError(ValueError):
    """A COLMAP model that cannot be read; the message names the file and the field."""

    def __init__(self, path: Path | str, field: str | None, problem: str):
        where = f"{path}" + (f" [{field}]" if field else "")
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True, eq=False)
class ColmapModel:
    """Fields:
        folder: the model folder read.
        binary: True for ``.bin`` files, False for ``.txt``.
        image_names: names in file order.
        world_to_camera: ``[N, 4, 4]`` float64 (OpenCV axes), unit-normalized quaternions.
        points: ``[P, 3]`` float64 3D points in file order.
    """

    folder: Path
    binary: bool
    image_names: tuple[str, ...]
    world_to_camera: np.ndarray
    points: np.ndarray


def _model_files(folder: Path) -> tuple[Path, Path, bool] | None:
    for ext, binary in ((".bin", True), (".txt", False)):
        images, points = folder / f"images{ext}", folder / f"points3D{ext}"
        if images.is_file() and points.is_file():
            return images, points, binary
    return None


def find_colmap_model(path: Path | str) -> Path:
    """The model folder: ``path`` itself when it holds a model, else ``path/sparse/0``, else ``path/sparse``."""
    path = Path(path)
    if not path.is_dir():
        raise ColmapModelError(path, None, "no such COLMAP model folder")
    for folder in (path, path / "sparse" / "0", path / "sparse"):
        if folder.is_dir() and _model_files(folder) is not None:
            return folder
    raise ColmapModelError(path, None, "no COLMAP model here (expected images.{bin,txt} and points3D.{bin,txt} "
                                       "in this folder, sparse/0/ or sparse/)")


def read_colmap_model(path: Path | str) -> ColmapModel:
    """Image poses and 3D points of the COLMAP model at ``path`` (see ``find_colmap_model``)."""
    folder = find_colmap_model(path)
    images_path, points_path, binary = _model_files(folder)
    if binary:
        names, qt = _read_images_binary(images_path)
        points = _read_points_binary(points_path)
    else:
        names, qt = _read_images_text(images_path)
        points = _read_points_text(points_path)
    if not names:
        raise ColmapModelError(images_path, None, "no images")
    if len(set(names)) != len(names):
        raise ColmapModelError(images_path, "NAME", "duplicate image names")
    qt = np.asarray(qt, dtype=np.float64).reshape(-1, 7)
    bad = ~np.isfinite(qt).all(axis=1)
    if bad.any():
        raise ColmapModelError(images_path, f"image {names[int(np.argmax(bad))]!r}", "pose holds NaN/Inf")
    norms = np.linalg.norm(qt[:, :4], axis=1)
    if (norms < COLMAP_QUAT_NORM_EPS).any():
        raise ColmapModelError(images_path, f"image {names[int(np.argmax(norms < COLMAP_QUAT_NORM_EPS))]!r} QVEC",
                               "zero quaternion")
    w2c = np.tile(np.eye(4), (len(names), 1, 1))
    w2c[:, :3, :3] = quats_to_rotmats(qt[:, :4] / norms[:, None])
    w2c[:, :3, 3] = qt[:, 4:]
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise ColmapModelError(points_path, "XYZ", "holds NaN/Inf")
    return ColmapModel(folder, binary, tuple(names), w2c, points)


# --- text ----------------------------------------------------------------------------------------


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ColmapModelError(path, None, f"cannot read ({exc})") from None


def _floats(parts: list[str], path: Path, field: str) -> list[float]:
    try:
        return [float(x) for x in parts]
    except ValueError:
        raise ColmapModelError(path, field, f"expected numbers, got {' '.join(parts)!r}") from None


def _read_images_text(path: Path) -> tuple[list[str], list[list[float]]]:
    """Two lines per image (the second, the 2D points, may be empty); comments and blank lines between images."""
    lines = _read_lines(path)
    names, qt = [], []
    i = 0
    while i < len(lines):
        line = lines[i].strip()
        if not line or line.startswith("#"):
            i += 1
            continue
        parts = line.split()
        if len(parts) < 10:
            raise ColmapModelError(path, f"line {i + 1}", "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
        names.append(" ".join(parts[9:]))
        qt.append(_floats(parts[1:8], path, f"line {i + 1} QW..TZ"))
        i += 2  # the next line lists the image's 2D points
    return names, qt


def _read_points_text(path: Path) -> list[list[float]]:
    points = []
    for number, raw in enumerate(_read_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 8:
            raise ColmapModelError(path, f"line {number}", "expected POINT3D_ID X Y Z R G B ERROR TRACK[]")
        points.append(_floats(parts[1:4], path, f"line {number} X Y Z"))
    return points


# --- binary --------------------------------------------------------------------------------------


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as exc:
            raise ColmapModelError(path, None, f"cannot read ({exc})") from None
        self.pos = 0

    def take(self, size: int, field: str) -> bytes:
        if size < 0 or self.pos + size > len(self.data):
            raise ColmapModelError(self.path, field, f"file ends at byte {len(self.data)}, truncated")
        out = self.data[self.pos:self.pos + size]
        self.pos += size
        return out

    def count(self, field: str) -> int:
        return _U64.unpack(self.take(8, field))[0]

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise ColmapModelError(self.path, None, f"{len(self.data) - self.pos} bytes after the last entry")


def _read_images_binary(path: Path) -> tuple[list[str], list[list[float]]]:
    reader = _Reader(path)
    names, qt = [], []
    for index in range(reader.count("num_images")):
        field = f"image {index}"
        values = _IMAGE_HEAD.unpack(reader.take(_IMAGE_HEAD.size, field))
        end = reader.data.find(b"\x00", reader.pos)
        if end < 0:
            raise ColmapModelError(path, f"{field} name", "no NUL terminator, truncated")
        raw = reader.take(end - reader.pos + 1, f"{field} name")[:-1]
        try:
            names.append(raw.decode("utf-8"))
        except UnicodeDecodeError:
            raise ColmapModelError(path, f"{field} name", "not UTF-8") from None
        qt.append(list(values[1:8]))
        reader.take(_POINT2D * reader.count(f"{field} num_points2D"), f"{field} points2D")
    reader.finish()
    return names, qt


def _read_points_binary(path: Path) -> np.ndarray:
    reader = _Reader(path)
    count = reader.count("num_points")
    points = np.empty((count, 3)) if count * _POINT_HEAD.size <= len(reader.data) else None
    if points is None:
        raise ColmapModelError(path, "num_points", f"{count} points cannot fit in {len(reader.data)} bytes")
    for index in range(count):
        values = _POINT_HEAD.unpack(reader.take(_POINT_HEAD.size, f"point {index}"))
        points[index] = values[1:4]
        reader.take(_TRACK_ELEMENT * reader.count(f"point {index} track_length"), f"point {index} track")
    reader.finish()
    return points
