"""Flat parts of many shapes for teaching benches and tests: brackets, plates, spacers, clips...

Each family draws a part type at random (its sizes, holes, height) as an `ExtrudedPart` in its own
frame, the origin at the footprint's area centroid (holes taken out). Some families come in pairs
that differ only by one hole or by being mirror images, so a finder must tell them apart.

    types = random_types(seed=5)                       # {name: ExtrudedPart}, 8+ families
    scene = layout([types["l-bracket"], ...], rng, area_mm=(0, 0, 200, 150))
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from cell.sim.parts import ExtrudedPart, FreeSpace

Poly = np.ndarray


def circle(cx: float, cy: float, r: float, n: int = 72) -> Poly:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])


def rect(x0: float, y0: float, x1: float, y1: float) -> Poly:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)


def _moments(poly: Poly) -> tuple[float, float, float]:
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    c = x * yn - xn * y
    a = c.sum() / 2
    s = np.sign(a) or 1.0
    return abs(a), s * ((x + xn) * c).sum() / 6, s * ((y + yn) * c).sum() / 6


def make_part(name: str, outline: Poly, holes: Sequence[Poly], height_mm: float) -> ExtrudedPart:
    """The part with its origin moved to its footprint's area centroid (holes taken out)."""
    a, sx, sy = _moments(outline)
    for h in holes:
        ha, hx, hy = _moments(h)
        a, sx, sy = a - ha, sx - hx, sy - hy
    c = np.array([sx / a, sy / a])
    return ExtrudedPart(name, outline - c, tuple(h - c for h in holes), float(height_mm))


def mirrored(part: ExtrudedPart, name: str) -> ExtrudedPart:
    flip = np.array([1.0, -1.0])
    return ExtrudedPart(
        name, part.outline_mm[::-1] * flip, tuple(h[::-1] * flip for h in part.holes_mm), part.height_mm
    )


def l_bracket(rng: np.random.Generator) -> ExtrudedPart:
    a, b = rng.uniform(32, 45), rng.uniform(18, 26)  # arms of different lengths: a mirror is another part
    w = rng.uniform(8, 11)
    outline = np.array([[0, 0], [a, 0], [a, w], [w, w], [w, b], [0, b]], dtype=np.float64)
    holes = [circle(a - w / 2 - 1, w / 2, rng.uniform(1.6, 2.2)), circle(w / 2, b - w / 2 - 1, rng.uniform(1.6, 2.2))]
    return make_part("l-bracket", outline, holes, rng.uniform(2, 4))


def t_bracket(rng: np.random.Generator) -> ExtrudedPart:
    a, b, w = rng.uniform(34, 44), rng.uniform(22, 30), rng.uniform(8, 10)
    outline = np.array(
        [[-a / 2, 0], [a / 2, 0], [a / 2, w], [w / 2, w], [w / 2, b], [-w / 2, b], [-w / 2, w], [-a / 2, w]],
        dtype=np.float64,
    )
    holes = [circle(-a / 2 + w / 2, w / 2, 1.8), circle(a / 2 - w / 2, w / 2, 1.8), circle(0, b - w / 2, 1.8)]
    return make_part("t-bracket", outline, holes, rng.uniform(2, 4))


def hole_plate(rng: np.random.Generator) -> ExtrudedPart:
    a, b = rng.uniform(30, 40), rng.uniform(18, 24)
    holes = [circle(5, 5, 1.8), circle(a - 5, 5, 1.8), circle(a - 5, b - 5, 1.8), circle(a / 2 - 3, b / 2 + 2, 2.5)]
    return make_part("plate-4h", rect(0, 0, a, b), holes, rng.uniform(2, 3))


def spacer(rng: np.random.Generator) -> ExtrudedPart:
    d = rng.uniform(13, 16)
    return make_part("spacer", circle(0, 0, d / 2, 96), [circle(0, 0, rng.uniform(3.0, 4.0), 72)], rng.uniform(4, 6))


def tab_washer(rng: np.random.Generator) -> ExtrudedPart:
    r, tabs = rng.uniform(9, 11), 3
    pts = []
    for i in range(96):
        a = 2 * np.pi * i / 96
        bump = 3.5 if (a % (2 * np.pi / tabs)) < 0.35 else 0.0
        pts.append([(r + bump) * math.cos(a), (r + bump) * math.sin(a)])
    return make_part("tab-washer", np.array(pts), [circle(0, 0, r * 0.45, 72)], rng.uniform(1.5, 2.5))


def clip(rng: np.random.Generator) -> ExtrudedPart:
    a, b, s = rng.uniform(24, 30), rng.uniform(14, 18), rng.uniform(4, 6)  # a slot s wide, from one end
    depth = a * 0.6
    outline = np.array(
        [
            [0, 0],
            [a, 0],
            [a, b],
            [0, b],
            [0, b / 2 + s / 2],
            [depth, b / 2 + s / 2],
            [depth, b / 2 - s / 2],
            [0, b / 2 - s / 2],
        ],
        dtype=np.float64,
    )
    return make_part("clip", outline, [circle(a - 5, b / 2, 1.8)], rng.uniform(2, 3))


def screw(rng: np.random.Generator, length_mm: float) -> ExtrudedPart:
    """A pan-head screw lying on its side, seen from above, as a flat stand-in (head and shank)."""
    head_d, head_k, d = 9.0, 3.5, 5.0
    outline = np.array(
        [[0, -head_d / 2], [head_k, -head_d / 2], [head_k, -d / 2], [head_k + length_mm, -d / 2],
         [head_k + length_mm, d / 2], [head_k, d / 2], [head_k, head_d / 2], [0, head_d / 2]],
        dtype=np.float64,
    )  # fmt: skip
    return make_part(f"screw-{length_mm:g}", outline, [], 4.0)


def gear(rng: np.random.Generator) -> ExtrudedPart:
    """Six teeth: 6-fold symmetric."""
    r, teeth = rng.uniform(8, 10), 6
    pts = []
    for i in range(144):
        a = 2 * np.pi * i / 144
        tooth = 2.5 if (a % (2 * np.pi / teeth)) < (np.pi / teeth) else 0.0
        pts.append([(r + tooth) * math.cos(a), (r + tooth) * math.sin(a)])
    return make_part("gear", np.array(pts), [circle(0, 0, 3.0, 72)], rng.uniform(3, 5))


FAMILIES: dict[str, Callable[[np.random.Generator], ExtrudedPart]] = {
    "l-bracket": l_bracket,
    "t-bracket": t_bracket,
    "plate-4h": hole_plate,
    "spacer": spacer,
    "tab-washer": tab_washer,
    "clip": clip,
    "gear": gear,
}


def random_types(seed: int) -> dict[str, ExtrudedPart]:
    """One part type per family drawn at random, plus the pairs a finder must tell apart: the L
    bracket's mirror image, the plate with one hole less, screws of three lengths."""
    rng = np.random.default_rng(seed)
    types = {name: make(rng) for name, make in FAMILIES.items()}
    types["l-bracket-mirror"] = mirrored(types["l-bracket"], "l-bracket-mirror")
    plate = types["plate-4h"]
    types["plate-3h"] = make_part("plate-3h", plate.outline_mm, list(plate.holes_mm[:3]), plate.height_mm)
    for length in (16.0, 20.0, 25.0):
        s = screw(rng, length)
        types[s.name] = s
    return types


def layout(
    parts: Sequence[ExtrudedPart],
    rng: np.random.Generator,
    area_mm: tuple[float, float, float, float],
    gap_mm: float = 6.0,
    tries: int = 400,
) -> list[ExtrudedPart]:
    """The parts placed at random positions and angles inside `area_mm`, at least `gap_mm` apart
    seen from above; a part that finds no room is left out."""
    x0, y0, x1, y1 = area_mm
    space = FreeSpace(area_mm, gap_mm)
    placed: list[ExtrudedPart] = []
    for part in parts:
        for _ in range(tries):
            p = part.placed(float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1)), float(rng.uniform(0, 360)))
            if space.claim(p.top_view_outline_mm()):
                placed.append(p)
                break
    return placed
