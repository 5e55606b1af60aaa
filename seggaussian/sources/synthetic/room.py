"""Procedural furnished rooms: quad-grid meshes with per-vertex textures and per-object labels.

A room is a closed box (floor, four walls, ceiling) with a door and windows, furnished with
parametric furniture (``furniture``) composed of boxes, cylinders, ellipsoids and draped sheets. Every
surface is a grid of quads built by ``mesh._Builder`` and coloured by a texture of ``textures``.

Two styles: ``scannetpp`` (warm palette, boxy furniture, bookshelf with books) and ``replica``
(cool pastel palette, round legs and tables, open shelves), so that cross-domain evaluation sees a
real change of appearance. All randomness comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.sources.synthetic.furniture import (_build_bed, _build_bookshelf, _build_box, _build_cabinet,
                                                     _build_chair, _build_plant, _build_sofa, _build_table,
                                                     _build_trash, _build_tv, _palette)
from seggaussian.sources.synthetic.mesh import EMBED, RoomConfig, RoomMesh, _Builder
from seggaussian.sources.synthetic.textures import blobs, checker, plain, planks, stripes, wood

#: Free space kept between neighbouring items along a wall (metres).
ITEM_GAP = 0.1
#: Free floor kept between items on opposite walls (metres).
PASSAGE = 0.6
#: The room shell (floor, ceiling, walls) extends this far past its edges for the same reason as ``EMBED``.
SHELL_OVERLAP = 0.03


class _Wall(NamedTuple):
    origin: np.ndarray  # [3] wall start at floor level
    along: np.ndarray  # [3] unit vector along the wall
    inward: np.ndarray  # [3] unit normal into the room
    length: float


def _wall_frame(wall: _Wall, s: float, offset: float = 0.0) -> np.ndarray:
    """Item frame: x along the wall, y into the room, z up; origin at ``s`` along the wall."""
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = wall.along, wall.inward, (0, 0, 1)
    m[:3, 3] = wall.origin + s * wall.along + (offset - EMBED) * wall.inward - np.array([0, 0, EMBED])
    return m


def build_room(rng: np.random.Generator, config: RoomConfig = RoomConfig()) -> RoomMesh:
    """A furnished room; every random choice comes from ``rng``."""
    replica = config.style == "replica"
    pal = _palette(config.style, rng)
    size = np.array([rng.uniform(3.8, 5.0), rng.uniform(3.4, 4.4), rng.uniform(2.5, 2.8)])
    offset = np.round(rng.uniform(-3, 3, size=3) * [1, 1, 0.2], 3)  # real meshes are not at the origin
    lo, hi = offset, offset + size
    light = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 1.0])
    b = _Builder(config, light)

    # shell: floor, ceiling, walls (normals into the room)
    floor_tex = checker(pal.floor, np.multiply(pal.floor, 0.85), 0.4, rng) if replica else planks(pal.floor, rng)
    o = SHELL_OVERLAP
    b.patch(b.new_object("floor"), lo - [o, o, 0], (0, size[1] + 2 * o, 0), (size[0] + 2 * o, 0, 0), floor_tex)
    b.patch(b.new_object("ceiling"), (lo[0] - o, lo[1] - o, hi[2]), (size[0] + 2 * o, 0, 0), (0, size[1] + 2 * o, 0), plain((0.95, 0.95, 0.94), rng, 0.02))
    corners = [lo, lo + [size[0], 0, 0], lo + [size[0], size[1], 0], lo + [0, size[1], 0]]
    walls = []
    wall_tex = plain(pal.wall, rng, 0.04) if replica else stripes(pal.wall, np.multiply(pal.wall, 0.94), 0.16, rng)
    for k in range(4):
        a, c = corners[k], corners[(k + 1) % 4]
        along = (c - a) / np.linalg.norm(c - a)
        inward = np.cross([0, 0, 1.0], along)
        walls.append(_Wall(a, along, inward, float(np.linalg.norm(c - a))))
        b.patch(b.new_object("wall"), a - o * along - [0, 0, o], (c - a) + 2 * o * along, (0, 0, size[2] + 2 * o), wall_tex)

    occupied: list[tuple[int, float, float, float]] = []  # (wall, s0, s1, depth) footprints along walls
    window_spans: list[tuple[int, float, float]] = []

    def free(wall: int, s0: float, s1: float, depth: float, tall: bool) -> bool:
        if s0 < 0.05 or s1 > walls[wall].length - 0.05:
            return False
        length = walls[wall].length
        for w2, a0, a1, d2 in occupied:
            if w2 == wall and s0 < a1 + ITEM_GAP and a0 < s1 + ITEM_GAP:
                return False
            # facing items on the opposite wall (its s runs the other way) must leave a passage
            if w2 == (wall + 2) % 4 and s0 < length - a0 and length - a1 < s1 and depth + d2 > walls[(wall + 1) % 4].length - PASSAGE:
                return False
            # corner clash with a neighbouring wall's item
            nxt, prv = (wall + 1) % 4, (wall - 1) % 4
            if w2 == nxt and s1 > walls[wall].length - d2 and a0 < depth:
                return False
            if w2 == prv and s0 < d2 and a1 > walls[w2].length - depth:
                return False
        if tall:
            for w2, a0, a1 in window_spans:
                if w2 == wall and s0 < a1 and a0 < s1:
                    return False
        return True

    def place(width: float, depth: float, tall: bool, walls_allowed=(0, 1, 2, 3)):
        for _ in range(60):
            wall = int(rng.choice(walls_allowed))
            s0 = rng.uniform(0.05, max(0.06, walls[wall].length - width - 0.05))
            if free(wall, s0, s0 + width, depth, tall):
                occupied.append((wall, s0, s0 + width, depth))
                return wall, s0
        return None

    # door (with frame) on a random wall, keeping its swing area free
    door_wall = int(rng.integers(4))
    ds = rng.uniform(0.3, walls[door_wall].length - 1.3)
    occupied.append((door_wall, ds - 0.1, ds + 1.0, 1.0))
    b.transform = _wall_frame(walls[door_wall], ds)
    door = b.new_object("door")
    door_col = pal.wood if not replica else (0.96, 0.96, 0.96)
    b.box(door, (-EMBED, 0.0, 0.0), (0.9 + EMBED, 0.04, 2.05 + EMBED), wood(door_col, rng), skip=("-z", "-y"))
    frame = b.new_object("doorframe")
    ftex = plain((0.97, 0.97, 0.95), rng, 0.02)
    b.box(frame, (-0.08, 0.0, 0.0), (0.0, 0.06, 2.13), ftex, skip=("-z", "-y"))
    b.box(frame, (0.9, 0.0, 0.0), (0.98, 0.06, 2.13), ftex, skip=("-z", "-y"))
    b.box(frame, (0.0, 0.0, 2.05), (0.9, 0.06, 2.13), ftex, skip=("-y",))

    # windows with frame, sill, curtain (or blinds) on other walls
    n_windows = int(rng.integers(1, 3))
    for window_index, wall in enumerate([w for w in rng.permutation(4) if w != door_wall][:n_windows]):
        ww = rng.uniform(0.9, 1.5)
        spot = place(ww + 1.1, 0.05, False, (int(wall),))
        if spot is None:
            continue
        wall, s0 = spot
        occupied.pop()  # low furniture may stand under a window
        window_spans.append((wall, s0, s0 + ww + 1.1))
        b.transform = _wall_frame(walls[wall], s0 + 0.55)
        z0, z1 = 0.95, min(2.25, size[2] - 0.2)
        win = b.new_object("window")
        b.patch(win, (-0.03, 0.02, z0 - 0.03), (0, 0, z1 - z0 + 0.06), (ww + 0.06, 0, 0), lambda st, pos: np.array([0.72, 0.85, 0.97]) * (1 + 0.15 * st[:, 1:2] / 2) + 0.05 * np.sin(st[:, :1] * 3))
        wf = b.new_object("window frame")
        ftx = plain((0.96, 0.96, 0.96) if not replica else (0.3, 0.3, 0.32), rng, 0.02)
        for (x0, x1, za, zb) in ((-0.06, 0, z0 - 0.02, z1), (ww, ww + 0.06, z0 - 0.02, z1), (-0.06, ww + 0.06, z1, z1 + 0.06), (ww / 2 - 0.025, ww / 2 + 0.025, z0 - 0.02, z1)):
            b.box(wf, (x0, 0, za), (x1, 0.05, zb), ftx, skip=("-y",))
        sill = b.new_object("windowsill")
        b.box(sill, (-0.1, 0, z0 - 0.04), (ww + 0.1, 0.16, z0), plain((0.9, 0.9, 0.88), rng, 0.03), skip=("-y",))
        if not replica or window_index == 0 or rng.uniform() < 0.5:  # Replica: blinds on later windows
            for side in (-1, 1):
                cur = b.new_object("curtain")
                cw = rng.uniform(0.35, 0.5)
                x0 = -cw - 0.02 if side < 0 else ww + 0.02
                z_start = 0.05 if rng.uniform() < 0.5 else z0 - 0.3
                b.sheet(cur, (x0, 0.06, z_start), cw, z1 + 0.1 - z_start, 0.06, 0.14,
                        stripes(pal.accent, np.multiply(pal.accent, 0.7), 0.12, rng) if not replica else plain(pal.accent, rng))
        else:
            bl = b.new_object("blinds")
            b.patch(bl, (0, 0.08, z1 - 0.6), (0, 0, 0.6), (ww, 0, 0), stripes((0.9, 0.9, 0.9), (0.7, 0.7, 0.7), 0.04, rng, axis=1))
        if rng.uniform() < 0.6:
            spot = place(ww * 0.8, 0.1, False, (wall,))
            if spot is not None:
                b.transform = _wall_frame(walls[spot[0]], spot[1], 0.04)
                heat = b.new_object("heater")
                b.box(heat, (0, 0, 0.15), (ww * 0.8, 0.08, 0.65), stripes((0.95, 0.95, 0.95), (0.8, 0.8, 0.8), 0.04, rng), skip=("-y",))

    # furniture along walls (unseen classes first so they almost always fit)
    def put(width, depth, tall, build, offset_in=0.0):
        spot = place(width, depth, tall)
        if spot is None:
            return False
        b.transform = _wall_frame(walls[spot[0]], spot[1], offset_in)
        build()
        return True

    bw, bd = rng.uniform(1.0, 1.6), rng.uniform(1.9, 2.1)
    put(bw, bd, False, lambda: _build_bed(b, rng, pal, replica, bw, bd))
    sw, sd = rng.uniform(1.6, 2.1), rng.uniform(0.8, 0.95)
    put(sw, sd, False, lambda: _build_sofa(b, rng, pal, replica, sw, sd))
    kw, kd, kh = rng.uniform(0.7, 1.0), rng.uniform(0.3, 0.38), rng.uniform(1.6, 2.0)
    put(kw, kd, True, lambda: _build_bookshelf(b, rng, pal, replica, kw, kd, kh))
    cw, cd, ch = rng.uniform(0.8, 1.2), rng.uniform(0.4, 0.5), rng.uniform(0.5, 0.8)

    def cabinet_with_tv():
        _build_cabinet(b, rng, pal, replica, cw, cd, ch)
        if rng.uniform() < 0.7:
            b.transform = b.transform @ _translate((cw * 0.1, 0.05, 0))
            _build_tv(b, rng, ch, cw * 0.8)

    put(cw, cd, False, cabinet_with_tv)
    dw, dd = rng.uniform(1.0, 1.4), rng.uniform(0.55, 0.7)

    def desk():
        _build_table(b, rng, pal, replica, dw, dd, key="desk")
        b.transform = b.transform @ _translate((dw * 0.3, 0.08, 0.74))
        mon = b.new_object("monitor")
        b.box(mon, (0, 0.0, 0.1), (0.55, 0.03, 0.43), plain((0.08, 0.08, 0.1), rng, 0.2))
        b.box(mon, (0.25, 0.0, -EMBED), (0.3, 0.03, 0.1), plain((0.15, 0.15, 0.15), rng), skip=("-z",))
        b.transform = b.transform @ _translate((0.1, dd, -0.74))
        _build_chair(b, rng, pal, replica)

    if rng.uniform() < 0.8:
        put(dw, dd + 0.6, False, desk)
    put(0.5, 0.5, False, lambda: _build_plant(b, rng, pal, replica))
    put(0.3, 0.3, False, lambda: _build_trash(b, rng, pal))
    for _ in range(int(rng.integers(1, 3))):
        size = rng.uniform(0.25, 0.45, size=3)
        put(size[0], size[1], False, lambda size=size: _build_box(b, rng, pal, size))
    put(0.3, 0.3, False, lambda: b.box(b.new_object("clutter"), (0, 0, 0), (0.3, 0.25, 0.2), plain((0.5, 0.5, 0.5), rng), skip=("-z",)))

    # pictures / whiteboard on walls (above furniture height)
    for k in range(int(rng.integers(1, 3))):
        wall = int(rng.integers(4))
        pw, ph = rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.6)
        s0 = rng.uniform(0.2, walls[wall].length - pw - 0.2)
        if any(w2 == wall and s0 < a1 and a0 < s0 + pw for w2, a0, a1 in window_spans) or (wall == door_wall and s0 < ds + 1.1 and ds - 0.2 < s0 + pw):
            continue
        b.transform = _wall_frame(walls[wall], s0)
        # ScanNet++ rooms (offices, classrooms) get a whiteboard as their first wall item: as the second one it
        # was in 6 of 45 train rooms of the benchmark profile (798 Gaussians), too few to learn (issue 16)
        key = "whiteboard" if (k == 0 and not replica) else "picture"
        pic = b.new_object(key)
        tex = plain((0.97, 0.97, 0.97), rng, 0.01) if key == "whiteboard" else blobs(rng)
        b.box(pic, (0, 0, 1.4), (pw, 0.025, 1.4 + ph), tex, skip=("-y",))

    # centre: rug, coffee table, ceiling lamp
    centre = 0.5 * (lo + hi)
    b.transform = _translate((centre[0] - 0.8, centre[1] - 0.6, lo[2]))
    b.patch(b.new_object("rug"), (0, 0, 0.015), (1.6, 0, 0), (0, 1.2, 0), checker(pal.accent, pal.fabric, 0.2, rng))
    if rng.uniform() < 0.5 and b.floor_is_clear((centre[0] - 0.45, centre[1] - 0.45, centre[0] + 0.45, centre[1] + 0.45), lo[2]):
        b.transform = _translate((centre[0] - 0.35, centre[1] - 0.3, lo[2] - EMBED))
        _build_table(b, rng, pal, replica, 0.7, 0.6 if not replica else 0.7)
    b.transform = _translate((centre[0], centre[1], hi[2]))
    lamp = b.new_object("ceiling lamp")
    r = rng.uniform(0.15, 0.25)
    b.cylinder(lamp, (0, 0, -0.12), r, 0.1, plain((1.0, 0.97, 0.85), rng, 0.02), caps=(True, False))
    b.transform = np.eye(4)
    return b.finish(lo, hi)


def _translate(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m
