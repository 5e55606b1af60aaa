"""Parametric furniture of the synthetic rooms: the two styles' palettes and one builder per piece (bed, sofa,
bookshelf, table, chair, cabinet, tv, plant, trash can, box), each composed of boxes, cylinders, ellipsoids and
draped sheets in its item frame (x along the wall, y into the room, z up).

Every builder adds its objects to the ``_Builder`` it is given and draws every random choice from ``rng``, in a
fixed order.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from seggaussian.sources.synthetic.mesh import EMBED, _Builder
from seggaussian.sources.synthetic.textures import Texture, checker, plain, stripes, wood


class _Palette(NamedTuple):
    wall: tuple
    floor: tuple
    wood: tuple
    fabric: tuple
    accent: tuple


def _palette(style: str, rng: np.random.Generator) -> _Palette:
    def pick(options):
        c = np.asarray(options[rng.integers(len(options))], float)
        return tuple(np.clip(c * rng.uniform(0.92, 1.08), 0, 1))

    if style == "replica":  # cool pastels, grey-blue wood, bright fabrics
        return _Palette(
            pick([(0.78, 0.84, 0.88), (0.85, 0.88, 0.80), (0.90, 0.86, 0.90)]),
            pick([(0.55, 0.58, 0.62), (0.70, 0.72, 0.74), (0.45, 0.50, 0.55)]),
            pick([(0.62, 0.64, 0.66), (0.85, 0.85, 0.85), (0.35, 0.38, 0.42)]),
            pick([(0.25, 0.45, 0.70), (0.30, 0.65, 0.60), (0.75, 0.35, 0.45)]),
            pick([(0.95, 0.75, 0.20), (0.20, 0.75, 0.85), (0.85, 0.30, 0.60)]),
        )
    return _Palette(  # warm: off-white walls, oak floors, earthy fabrics
        pick([(0.93, 0.90, 0.82), (0.88, 0.85, 0.80), (0.95, 0.93, 0.88)]),
        pick([(0.62, 0.45, 0.28), (0.72, 0.55, 0.36), (0.50, 0.36, 0.24)]),
        pick([(0.55, 0.38, 0.22), (0.70, 0.52, 0.32), (0.42, 0.28, 0.18)]),
        pick([(0.55, 0.30, 0.22), (0.40, 0.45, 0.30), (0.35, 0.35, 0.45), (0.60, 0.52, 0.40)]),
        pick([(0.80, 0.20, 0.15), (0.15, 0.35, 0.70), (0.85, 0.65, 0.15)]),
    )


def _legs(b: _Builder, obj: int, w: float, d: float, h: float, t: float, tex: Texture, round_legs: bool) -> None:
    for x, y in ((t, t), (w - t, t), (t, d - t), (w - t, d - t)):
        if round_legs:
            b.cylinder(obj, (x, y, 0.0), t * 0.6, h, tex, caps=(False, False))
        else:
            b.box(obj, (x - t / 2, y - t / 2, 0), (x + t / 2, y + t / 2, h), tex, skip=("-z", "+z"))


def _build_bed(b, rng, pal, replica, w, d):
    bed = b.new_object("bed")
    wood_t, fabric = wood(pal.wood, rng), plain((0.93, 0.92, 0.9) if not replica else (0.96, 0.96, 0.98), rng)
    b.box(bed, (0, 0.06, 0), (w, d, 0.3), wood_t, skip=("-z",))
    b.box(bed, (0.02, 0.08, 0.3), (w - 0.02, d - 0.02, 0.5), fabric, skip=("-z",))
    b.box(bed, (0, 0, 0), (w, 0.06, 0.95 if not replica else 0.8), wood_t if not replica else plain(pal.fabric, rng))
    blanket = b.new_object("blanket")
    b.box(blanket, (-0.02, d * 0.38, 0.5 - EMBED), (w + 0.02, d + 0.02, 0.54), checker(pal.fabric, np.multiply(pal.fabric, 0.7), 0.12, rng), skip=("-z",))
    b.patch(blanket, (-0.02, d * 0.38, 0.5), (0, 0, -0.28), (0, d * 0.62 + 0.02, 0), plain(pal.fabric, rng))
    b.patch(blanket, (w + 0.02, d * 0.38, 0.5), (0, d * 0.62 + 0.02, 0), (0, 0, -0.28), plain(pal.fabric, rng))
    n_pillows = 2 if w > 1.2 else 1
    for k in range(n_pillows):
        p = b.new_object("pillow")
        x0 = 0.1 + k * (w - 0.2) / n_pillows
        b.ellipsoid(p, (x0 + (w - 0.2) / n_pillows / 2, 0.3, 0.56), ((w - 0.3) / n_pillows / 2, 0.16, 0.07), stripes((1, 1, 1), pal.accent, 0.06, rng))


def _build_sofa(b, rng, pal, replica, w, d):
    sofa = b.new_object("sofa")
    fab = plain(pal.fabric, rng, 0.08) if replica else stripes(pal.fabric, np.multiply(pal.fabric, 0.85), 0.05, rng, axis=1)
    seat = 0.42 if not replica else 0.36
    b.box(sofa, (0, 0, 0.08), (w, d, seat), fab)
    b.box(sofa, (0, 0, seat), (w, 0.2, 0.85 if not replica else 0.7), fab, skip=("-z",))
    for x0 in (0.0, w - 0.16):
        b.box(sofa, (x0, 0.2, seat), (x0 + 0.16, d, seat + 0.2), fab, skip=("-z",))
    _legs(b, sofa, w, d, 0.08, 0.05, wood(pal.wood, rng), replica)
    for k in range(2):
        c = b.new_object("cushion")
        x0 = 0.25 + k * (w - 0.9)
        b.box(c, (x0, 0.22, seat - EMBED), (x0 + 0.4, 0.34, seat + 0.38), checker(pal.accent, (0.95, 0.95, 0.9), 0.05, rng), skip=("-z",))


def _build_bookshelf(b, rng, pal, replica, w, d, h):
    key = "shelf" if replica else "bookshelf"
    shelf = b.new_object(key)
    tex = wood(pal.wood, rng)
    t = 0.025
    b.box(shelf, (0, 0, 0), (t, d, h), tex)
    b.box(shelf, (w - t, 0, 0), (w, d, h), tex)
    b.box(shelf, (t, 0.03, 0), (w - t, 0.04, h), tex)  # back panel, 2 cm off the wall
    levels = np.linspace(0.05, h - t, 5)
    books = []
    for z in levels:
        b.box(shelf, (t, 0, z - t), (w - t, d, z), tex)
        if z > h - 0.2:
            continue
        x = t + 0.02
        while x < w - t - 0.06 and rng.uniform() < 0.93:
            bw, bh = rng.uniform(0.025, 0.06), rng.uniform(0.18, 0.3)
            if x + bw > w - t:
                break
            bk = b.new_object("book")
            col = rng.uniform(0.1, 0.9, size=3)
            b.box(bk, (x, 0.07, z - EMBED), (x + bw, d - 0.02, z + bh), stripes(col, col * 0.6, bh / 2.5, rng, axis=1), skip=("-z",))
            books.append(bk)
            x += bw + rng.uniform(0.0, 0.02)
    b.set_contains(shelf, books)


def _build_table(b, rng, pal, replica, w, d, key="table"):
    table = b.new_object(key)
    tex = wood(pal.wood, rng)
    if replica:
        r = min(w, d) / 2
        b.cylinder(table, (w / 2, d / 2, 0.71), r, 0.04, tex, caps=(True, True))
        b.cylinder(table, (w / 2, d / 2, 0.0), 0.05, 0.71, tex, caps=(False, False))
    else:
        b.box(table, (0, 0, 0.7), (w, d, 0.74), tex)
        _legs(b, table, w, d, 0.7, 0.05, tex, False)


def _build_chair(b, rng, pal, replica):
    chair = b.new_object("chair")
    tex = plain(pal.fabric, rng) if replica else wood(pal.wood, rng)
    b.box(chair, (0, 0, 0.43), (0.45, 0.45, 0.47), tex)
    b.box(chair, (0, 0.41, 0.47), (0.45, 0.45, 0.9), tex)
    _legs(b, chair, 0.45, 0.45, 0.43, 0.04, tex, replica)


def _build_cabinet(b, rng, pal, replica, w, d, h):
    cab = b.new_object("cabinet")
    colour = pal.wood if not replica else (0.92, 0.92, 0.92)
    b.box(cab, (0, 0, 0), (w, d, h), plain(colour, rng), skip=("-z",))
    n = 2
    for k in range(n):  # two door panels on the front (+y), a darker handle band near the top
        x0 = k * w / n
        panel = stripes(np.multiply(colour, 0.9), np.multiply(colour, 0.5), 0.5, rng, axis=1)
        b.box(cab, (x0 + 0.02, d, 0.05), (x0 + w / n - 0.02, d + 0.015, h - 0.05), panel, skip=("-y",))
    return cab


def _build_tv(b, rng, on_z, w):
    tv = b.new_object("tv")
    b.box(tv, (0, 0.02, on_z + 0.25), (w, 0.07, on_z + 0.25 + w * 0.56), plain((0.05, 0.05, 0.06), rng, 0.3))
    b.box(tv, (w / 2 - 0.03, 0.03, on_z - EMBED), (w / 2 + 0.03, 0.06, on_z + 0.25), plain((0.1, 0.1, 0.1), rng), skip=("-z",))


def _build_plant(b, rng, pal, replica):
    pot = b.new_object("plant pot")
    r = rng.uniform(0.11, 0.16)
    c = 0.25  # centre of the 0.5 m footprint; the foliage (radius <= 0.24 m) stays inside it
    b.cylinder(pot, (c, c, 0), r, 0.35, stripes((0.75, 0.4, 0.25), (0.65, 0.33, 0.2), 0.05, rng, axis=1), caps=(False, False))
    plant = b.new_object("plant")
    leafy = lambda st, pos: np.array([0.18, 0.45, 0.15]) * (1 + 0.35 * _leaf_noise(pos))[:, None]  # noqa: E731
    b.ellipsoid(plant, (c, c, 0.35 + r * 2.2), (r * 1.5, r * 1.5, r * 2.4), leafy)


def _leaf_noise(pos):
    return np.sin(pos[:, 0] * 41.0) * np.sin(pos[:, 1] * 37.0) * np.sin(pos[:, 2] * 29.0)


def _build_trash(b, rng, pal):
    can = b.new_object("trash can")
    b.cylinder(can, (0.15, 0.15, 0), 0.15, 0.4, plain(pal.accent, rng), caps=(False, False))


def _build_box(b, rng, pal, size):
    box = b.new_object("box")
    b.box(box, (0, 0, 0), size, plain((0.72, 0.55, 0.35), rng, 0.1), skip=("-z",))
