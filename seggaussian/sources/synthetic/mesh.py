"""The mesh of a synthetic room: its object classes, the mesh type and the quad-grid builder every surface is
made with.

Every surface is a grid of quads with edges no longer than ``RoomConfig.max_edge`` so that vertex colours carry
the texture patterns (planks, stripes, fabric checks, book spines, ...). Colours include a baked Lambertian shading
term, as the vertex colours of a real scan include lighting.

Each object carries a class key of ``CLASS_TABLE``: its top-100 name, the raw ScanNet++ label the generator writes
(renamed / dropped through the ``map_benchmark.csv`` it writes) and its Replica class name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from seggaussian.sources.synthetic.textures import Texture

#: class key -> (top-100 name or None, raw ScanNet++ label, Replica class name or None for void).
CLASS_TABLE: dict[str, tuple[str | None, str, str | None]] = {
    "wall": ("wall", "wall", "wall"),
    "floor": ("floor", "floor", "floor"),
    "ceiling": ("ceiling", "ceiling", "ceiling"),
    "door": ("door", "door", "door"),
    "doorframe": ("doorframe", "door frame", "door"),
    "window": ("window", "window", "window"),
    "window frame": ("window frame", "window frame", "window"),
    "windowsill": ("windowsill", "window sill", "window"),
    "curtain": ("curtain", "curtain", "curtain"),
    "blinds": ("blinds", "blinds", "blinds"),
    "bookshelf": ("bookshelf", "bookshelf", "shelf"),
    "shelf": ("shelf", "shelf", "shelf"),
    "book": ("book", "books", "book"),
    "sofa": ("sofa", "sofa", "sofa"),
    "cushion": ("cushion", "cushion", "cushion"),
    "bed": ("bed", "bed", "bed"),
    "pillow": ("pillow", "pillow", "pillow"),
    "blanket": ("blanket", "blanket", "comforter"),
    "table": ("table", "table", "table"),
    "desk": ("table", "desk", "desk"),
    "chair": ("chair", "chair", "chair"),
    "cabinet": ("cabinet", "cabinet", "cabinet"),
    "tv": ("tv", "tv", "tv-screen"),
    "monitor": ("monitor", "monitor", "monitor"),
    "trash can": ("trash can", "trash can", "bin"),
    "plant": ("plant", "plant", "indoor-plant"),
    "plant pot": ("plant pot", "plant pot", "vase"),
    "ceiling lamp": ("ceiling lamp", "ceiling light", "lamp"),
    "picture": ("picture", "picture", "picture"),
    "whiteboard": ("whiteboard", "whiteboard", "panel"),
    "heater": ("heater", "heater", "panel"),
    "box": ("box", "cardboard box", "box"),
    "rug": (None, "rug", "rug"),  # kept by the map but not a top-100 class -> ignore
    "clutter": (None, "object", None),  # raw label dropped by the map (None); Replica void
}

#: raw ScanNet++ label -> semantic_map_to value written in map_benchmark.csv ("" keeps, "None" drops).
RAW_LABEL_MAP = {
    "wall": "", "floor": "", "ceiling": "", "door": "", "door frame": "doorframe", "window": "",
    "window frame": "", "window sill": "windowsill", "curtain": "", "blinds": "", "bookshelf": "",
    "shelf": "", "books": "book", "sofa": "", "cushion": "", "bed": "", "pillow": "", "blanket": "",
    "table": "", "desk": "table", "chair": "", "cabinet": "", "tv": "", "monitor": "", "trash can": "",
    "plant": "", "plant pot": "", "ceiling light": "ceiling lamp", "picture": "", "whiteboard": "",
    "heater": "", "cardboard box": "box", "rug": "", "object": "None",
}


@dataclass(frozen=True)
class RoomConfig:
    """How a synthetic room is built."""

    max_edge: float = 0.05
    """Longest quad edge in metres; vertex colours carry texture at this resolution."""
    style: str = "scannetpp"
    """``scannetpp`` (warm, boxy) or ``replica`` (cool pastel, round legs, open shelves)."""
    segment_size: float = 1.0
    """Edge of the square tiles a surface is cut into for ``segments.json`` (metres)."""


class SynthObject(NamedTuple):
    """One annotated object (instance).

    Fields:
        key: class key into ``CLASS_TABLE``.
        contains: indices of objects whose vertices this object's annotation group also covers
            (e.g. a bookshelf's group covers its books; the books keep their label by the
            smallest-instance rule).
    """

    key: str
    contains: tuple[int, ...] = ()


class RoomMesh(NamedTuple):
    """A synthetic room.

    Fields:
        vertices: ``[V, 3]`` float64 world positions (metres, z up).
        normals: ``[V, 3]`` float64 unit normals.
        colors: ``[V, 3]`` uint8 RGB (texture with baked shading).
        quads: ``[Q, 4]`` int64 vertex indices (some collapsed to triangles at cylinder caps/poles).
        vertex_object: ``[V]`` int64 index into ``objects``.
        vertex_segment: ``[V]`` int64 over-segmentation id (a surface tile), 0..S-1.
        objects: the annotated objects.
        room_min, room_max: ``[3]`` the room's inner box (floor corner, ceiling corner).
    """

    vertices: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    quads: np.ndarray
    vertex_object: np.ndarray
    vertex_segment: np.ndarray
    objects: tuple[SynthObject, ...]
    room_min: np.ndarray
    room_max: np.ndarray


#: Objects resting on or against another object are pushed this far into it (metres), so that no
#: vertex lies exactly on another object's surface: every contact edge is hidden inside geometry
#: and a visible vertex has one unambiguous label in the rendered label images.
EMBED = 0.01
#: Normals shorter than this (degenerate pole/cap vertices) are left unnormalized, not divided by ~0.
NORMAL_EPS = 1e-12
#: Slack when counting grid cells, so an exact multiple of max_edge does not gain a cell from rounding.
GRID_COUNT_EPS = 1e-9


class _Builder:
    """Accumulates quad grids; ``transform`` maps the current item frame to the world."""

    def __init__(self, config: RoomConfig, light: np.ndarray):
        self.config = config
        self.light = light / np.linalg.norm(light)
        self.transform = np.eye(4)
        self.vertices, self.normals, self.colors, self.quads = [], [], [], []
        self.vertex_object, self.vertex_segment = [], []
        self.objects: list[SynthObject] = []
        self.n_vertices = 0
        self.n_segments = 0

    def new_object(self, key: str, contains: tuple[int, ...] = ()) -> int:
        assert key in CLASS_TABLE, key
        self.objects.append(SynthObject(key, contains))
        return len(self.objects) - 1

    def set_contains(self, obj: int, contains) -> None:
        self.objects[obj] = self.objects[obj]._replace(contains=tuple(contains))

    def add_grid(self, obj: int, positions: np.ndarray, st: np.ndarray, normals: np.ndarray, texture: Texture) -> None:
        """A ``[nu+1, nv+1]`` grid of local positions, metric surface coords and normals."""
        nu, nv = positions.shape[0] - 1, positions.shape[1] - 1
        rot, trans = self.transform[:3, :3], self.transform[:3, 3]
        pos = positions.reshape(-1, 3) @ rot.T + trans
        nrm = normals.reshape(-1, 3) @ rot.T
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), NORMAL_EPS)
        st = st.reshape(-1, 2)
        albedo = np.clip(texture(st, pos), 0.0, 1.0)
        shade = 0.62 + 0.38 * np.abs(nrm @ self.light)
        rgb = np.clip(np.round(albedo * shade[:, None] * 255.0), 0, 255).astype(np.uint8)
        i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
        idx = lambda a, b: (a * (nv + 1) + b).ravel()  # noqa: E731
        quads = np.stack([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1), idx(i, j + 1)], axis=1) + self.n_vertices
        seg_size = self.config.segment_size
        tiles = np.floor(st / seg_size).astype(np.int64)
        _, seg = np.unique(tiles, axis=0, return_inverse=True)
        seg = seg.ravel()
        self.vertices.append(pos)
        self.normals.append(nrm)
        self.colors.append(rgb)
        self.quads.append(quads)
        self.vertex_object.append(np.full(len(pos), obj, dtype=np.int64))
        self.vertex_segment.append(seg + self.n_segments)
        self.n_segments += int(seg.max()) + 1
        self.n_vertices += len(pos)

    def _count(self, length: float) -> int:
        return max(1, int(math.ceil(length / self.config.max_edge - GRID_COUNT_EPS)))

    def patch(self, obj: int, origin, du, dv, texture: Texture) -> None:
        """A flat rectangle ``origin + a du + b dv`` (a, b in [0, 1]); normal along du x dv."""
        origin, du, dv = (np.asarray(x, float) for x in (origin, du, dv))
        lu, lv = np.linalg.norm(du), np.linalg.norm(dv)
        nu, nv = self._count(lu), self._count(lv)
        a = np.linspace(0, 1, nu + 1)[:, None, None]
        b = np.linspace(0, 1, nv + 1)[None, :, None]
        positions = origin + a * du + b * dv
        st = np.concatenate([np.broadcast_to(a * lu, positions.shape[:2] + (1,)), np.broadcast_to(b * lv, positions.shape[:2] + (1,))], axis=-1)
        normal = np.cross(du, dv)
        normal /= np.linalg.norm(normal)
        self.add_grid(obj, positions, st, np.broadcast_to(normal, positions.shape), texture)

    def box(self, obj: int, lo, hi, texture: Texture, skip: tuple[str, ...] = ()) -> None:
        """An axis-aligned (item frame) box with outward faces; ``skip`` names faces left out ('-z', ...)."""
        (x0, y0, z0), (x1, y1, z1) = np.asarray(lo, float), np.asarray(hi, float)
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        faces = {
            "-z": ((x0, y0, z0), (0, dy, 0), (dx, 0, 0)),
            "+z": ((x0, y0, z1), (dx, 0, 0), (0, dy, 0)),
            "-y": ((x0, y0, z0), (dx, 0, 0), (0, 0, dz)),
            "+y": ((x0, y1, z0), (0, 0, dz), (dx, 0, 0)),
            "-x": ((x0, y0, z0), (0, 0, dz), (0, dy, 0)),
            "+x": ((x1, y0, z0), (0, dy, 0), (0, 0, dz)),
        }
        for name, (o, du, dv) in faces.items():
            if name not in skip:
                self.patch(obj, o, du, dv, texture)

    def cylinder(self, obj: int, base, radius: float, height: float, texture: Texture, caps=(False, True)) -> None:
        """A vertical cylinder standing on ``base`` (item frame), with optional bottom/top caps."""
        base = np.asarray(base, float)
        nu = max(8, self._count(2 * np.pi * radius))
        nv = self._count(height)
        ang = np.linspace(0, 2 * np.pi, nu + 1)[:, None]
        z = np.linspace(0, height, nv + 1)[None, :]
        ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=-1)  # [nu+1, 1, 3]
        positions = base + radius * ring + z[..., None] * np.array([0, 0, 1.0])
        st = np.stack(np.broadcast_arrays(ang * radius, z), axis=-1)
        self.add_grid(obj, positions, st, np.broadcast_to(ring, positions.shape), texture)
        for cap, top in zip(caps, (False, True)):
            if not cap:
                continue
            nr = self._count(radius)
            r = np.linspace(radius, 0, nr + 1)[None, :, None]
            ang_c = ang if top else ang[::-1]
            ring_c = np.stack([np.cos(ang_c), np.sin(ang_c), np.zeros_like(ang_c)], axis=-1)
            pos = base + np.array([0, 0, height if top else 0.0]) + r * ring_c
            st_c = pos[..., :2] - base[:2]
            normal = np.array([0, 0, 1.0 if top else -1.0])
            self.add_grid(obj, pos, st_c, np.broadcast_to(normal, pos.shape), texture)

    def ellipsoid(self, obj: int, centre, radii, texture: Texture) -> None:
        centre, radii = np.asarray(centre, float), np.asarray(radii, float)
        nu = max(12, self._count(2 * np.pi * radii[:2].max()))
        # uniform latitude steps: a meridian moves at most max(radius) per radian of latitude
        nv = max(6, self._count(np.pi * radii.max()))
        lon = np.linspace(0, 2 * np.pi, nu + 1)[:, None]
        lat = np.linspace(-np.pi / 2, np.pi / 2, nv + 1)[None, :]
        unit = np.stack(np.broadcast_arrays(np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)), axis=-1)
        positions = centre + unit * radii
        normals = unit / radii
        st = np.stack(np.broadcast_arrays(lon * radii[:2].max(), lat * radii[2]), axis=-1)
        self.add_grid(obj, positions, st, normals, texture)

    def sheet(self, obj: int, origin, width: float, height: float, depth_amp: float, period: float, texture: Texture) -> None:
        """A hanging sheet in the item x-z plane at ``origin``, folded along x (a curtain), facing +y."""
        origin = np.asarray(origin, float)
        slope = depth_amp * np.pi / period  # steepest fold slope: arc length per unit width <= sqrt(1 + slope^2)
        nu, nv = self._count(width * np.sqrt(1 + slope ** 2)), self._count(height)
        x = np.linspace(0, width, nu + 1)[:, None]
        z = np.linspace(0, height, nv + 1)[None, :]
        phase = 2 * np.pi * x / period
        y = depth_amp * (0.5 + 0.5 * np.sin(phase)) * np.ones_like(z)
        positions = origin + np.stack(np.broadcast_arrays(x, y, z), axis=-1)
        slope = depth_amp * 0.5 * np.cos(phase) * 2 * np.pi / period
        normals = np.stack(np.broadcast_arrays(-slope, np.ones_like(slope), np.zeros_like(z)), axis=-1)
        st = np.stack(np.broadcast_arrays(x, z), axis=-1)
        self.add_grid(obj, positions, st, normals, texture)

    def floor_is_clear(self, rect, floor_z: float, height: float = 1.2) -> bool:
        """No furniture vertex (shell, rug and hanging things aside) in ``rect`` = (x0, y0, x1, y1) below ``height``."""
        vertices = np.concatenate(self.vertices)
        keys = np.array([o.key for o in self.objects])[np.concatenate(self.vertex_object)]
        p = vertices[~np.isin(keys, ("floor", "wall", "ceiling", "rug", "ceiling lamp"))]
        inside = (p[:, 0] > rect[0]) & (p[:, 0] < rect[2]) & (p[:, 1] > rect[1]) & (p[:, 1] < rect[3]) & (p[:, 2] < floor_z + height)
        return not inside.any()

    def finish(self, room_min, room_max) -> RoomMesh:
        return RoomMesh(
            np.concatenate(self.vertices), np.concatenate(self.normals), np.concatenate(self.colors),
            np.concatenate(self.quads), np.concatenate(self.vertex_object), np.concatenate(self.vertex_segment),
            tuple(self.objects), np.asarray(room_min, float), np.asarray(room_max, float),
        )
