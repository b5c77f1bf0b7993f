"""Drawing what the vision found on a frame, for an operator to read at a glance: shared by
`run-cell locate --annotate` and the operator screen.

Each part is outlined in its class's colour (bolt orange, nut green, unknown red and
dashed, so red and green are not the only difference), a small legend in the emptiest
corner says so, and each part carries at most one number: its place in the pick order when
an order is given, else its part id (the row of `run-cell locate`'s table). An unknown part
gets a short label ("washer?", "unknown"); the full reason stays in `LocatedPart.reason`.

Labels are placed by `layout()` so that none overlaps another label, the legend or another
part's outline box, and all stay inside the image: the eight places around the part first,
then the nearest free place (with a leader line to its part), then on the part itself. The
text is scaled to the image, so a 320 x 240 photo and a 4K frame read alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from cell.vision.types import LocatedPart, LocateResult

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 in image pixels; x1 and y1 exclusive

FONT = cv2.FONT_HERSHEY_SIMPLEX
COLOURS_BGR = {"bolt": (0, 140, 255), "nut": (0, 160, 0), "unknown": (40, 40, 220)}
TEXT_BGR = {"bolt": (0, 0, 0), "nut": (255, 255, 255), "unknown": (255, 255, 255)}
TAUGHT_BGR = (170, 60, 150)  # every taught part type (cell.vision.shapes)


def _colour(cls: str) -> tuple[int, int, int]:
    return COLOURS_BGR.get(cls, TAUGHT_BGR)


def _text_colour(cls: str) -> tuple[int, int, int]:
    return TEXT_BGR.get(cls, (255, 255, 255))


JAWS_BGR = (255, 80, 0)

# Unknown parts' short labels: the first of these words found in the reason decides.
SHORT_REASONS = [
    ("washer", "washer?"),
    ("border", "at edge"),
    ("debris", "debris?"),
    ("touching", "touching?"),
    ("coin", "coin?"),
    ("standing", "standing?"),
    ("on its side", "on side?"),
    ("no finite table position", "unmapped"),
]


@dataclass(frozen=True)
class Style:
    """Sizes in pixels for one image size: text about 1/45 of the shorter side, at least 10 px."""

    text_px: int
    font_scale: float
    thick: int  # outline and text stroke
    pad: int  # inside a label box, around its text
    gap: int  # between a part's outline box and its label

    @classmethod
    def for_size(cls, width_px: int, height_px: int) -> Style:
        text_px = int(np.clip(round(min(width_px, height_px) / 45), 10, 120))
        return cls(
            text_px=text_px,
            font_scale=text_px / 22.0,
            thick=max(1, round(text_px / 11)),
            pad=max(2, round(text_px * 0.25)),
            gap=max(2, round(text_px * 0.3)),
        )

    def box_size(self, text: str, scale: float = 1.0) -> tuple[int, int, int]:
        """(width, height, baseline) of a label box holding `text`, padding included."""
        (w, h), base = cv2.getTextSize(text, FONT, self.font_scale * scale, self.thick)
        return w + 2 * self.pad, h + base + 2 * self.pad, base


@dataclass(frozen=True)
class PlacedLabel:
    part_id: int
    cls: str
    text: str
    box_px: Box
    leader: bool  # placed away from its part: a line joins them


@dataclass
class Layout:
    """Where everything goes on one frame; what `annotate` draws and a test can measure."""

    image_size: tuple[int, int]
    style: Style
    part_boxes: dict[int, Box]  # each part's outline bounding box
    labels: list[PlacedLabel] = field(default_factory=list)
    unplaced: list[int] = field(default_factory=list)  # parts whose label found no free place (none drawn)
    legend_box: Box | None = None
    legend_items: list[tuple[str, str, Box]] = field(default_factory=list)  # (kind, text, box)


def short_reason(reason: str) -> str:
    """A few characters for the frame; the full reason goes to the screen's list and the table."""
    text = reason.lower()
    return next((short for word, short in SHORT_REASONS if word in text), "unknown")


def label_text(part: LocatedPart, number: int | None) -> str | None:
    """One number at most: `number` for a known part, the short reason (after it) for an unknown one."""
    if part.cls == "unknown":
        return short_reason(part.reason) if number is None else f"{number} {short_reason(part.reason)}"
    return None if number is None else str(number)


def layout(result: LocateResult, image_size: tuple[int, int], order: Sequence[int] | None = None) -> Layout:
    """Place the legend and every part's label on an image of `image_size` (w, h).

    `order`: part ids in the order the cell will pick them, numbered 1, 2, 3...; parts not in
    it get no number. None: every part is numbered with its id (as `run-cell locate` lists it).
    """
    w, h = image_size
    style = Style.for_size(w, h)
    boxes = {p.id: _part_box(p, style, w, h) for p in result.objects}
    out = Layout((w, h), style, boxes)
    _place_legend(out, result, order)
    rank = None if order is None else {part_id: n for n, part_id in enumerate(order, start=1)}
    wanted = []
    for p in result.objects:
        number = p.id if rank is None else rank.get(p.id)
        text = label_text(p, number)
        if text is not None:
            wanted.append((number if number is not None else 10**9, p, text))
    placed: list[Box] = [] if out.legend_box is None else [_grow(out.legend_box, style.gap)]
    pad = style.thick + 1  # an outline's stroke reaches beyond its box
    for _, p, text in sorted(wanted, key=lambda t: (t[0], t[1].id)):  # the next picks choose first
        others = [_grow(b, pad) for i, b in boxes.items() if i != p.id]
        got = _place(p, boxes[p.id], text, style, (w, h), others + placed)
        if got is None:
            out.unplaced.append(p.id)
            continue
        box, leader = got
        out.labels.append(PlacedLabel(p.id, p.cls, text, box, leader))
        placed.append(box)
    return out


def annotate(image: np.ndarray, result: LocateResult, order: Sequence[int] | None = None) -> np.ndarray:
    """The image with each part outlined in its class's colour, bolts with the line the jaws
    close along, one number per part (the pick order when `order` is given, else the part id),
    a short label on unknown parts, and a legend; see `layout` for where labels go."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    h, w = out.shape[:2]
    plan = layout(result, (w, h), order)
    style = plan.style
    parts = {p.id: p for p in result.objects}
    for p in result.objects:
        _draw_part(out, p, style)
    for label in plan.labels:
        if label.leader:
            _draw_leader(out, label, parts[label.part_id], style)
    for label in plan.labels:
        _draw_label(out, label, style)
    if plan.legend_box is not None:
        _draw_legend(out, plan, style)
    return out


# --- layout ---


def _part_box(p: LocatedPart, style: Style, w: int, h: int) -> Box:
    if p.outline_px is not None and len(p.outline_px):
        x, y, bw, bh = cv2.boundingRect(np.asarray(p.outline_px).reshape(-1, 1, 2))
        return x, y, x + bw, y + bh
    r = style.text_px // 2  # no outline (a record, not a frame): a marker's worth around the centre
    cx, cy = (int(round(v)) for v in p.pixel)
    return cx - r, cy - r, cx + r + 1, cy + r + 1


def _grow(b: Box, d: int) -> Box:
    return b[0] - d, b[1] - d, b[2] + d, b[3] + d


def _free(candidates: np.ndarray, obstacles: list[Box]) -> np.ndarray:
    """Which of the (K, 4) candidate boxes overlap none of the obstacles."""
    if not obstacles:
        return np.ones(len(candidates), bool)
    o = np.asarray(obstacles)[None, :, :]
    c = candidates[:, None, :]
    hit = (c[..., 0] < o[..., 2]) & (o[..., 0] < c[..., 2]) & (c[..., 1] < o[..., 3]) & (o[..., 1] < c[..., 3])
    return np.asarray(~hit.any(axis=1))


def _around(box: Box, lw: int, lh: int, gap: int, size: tuple[int, int]) -> np.ndarray:
    """The eight places beside a box, in order of preference, moved inside the image."""
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1) // 2, (y0 + y1) // 2
    xs = {"r": x1 + gap, "l": x0 - gap - lw, "c": cx - lw // 2}
    ys = {"a": y0 - gap - lh, "b": y1 + gap, "m": cy - lh // 2}
    order = [("r", "m"), ("c", "a"), ("l", "m"), ("c", "b"), ("r", "a"), ("l", "a"), ("r", "b"), ("l", "b")]
    return _inside(np.array([(xs[i], ys[j]) for i, j in order]), lw, lh, size)


def _inside(corners: np.ndarray, lw: int, lh: int, size: tuple[int, int]) -> np.ndarray:
    """(K, 2) top-left corners moved into the image, as (K, 4) boxes."""
    w, h = size
    x = np.clip(corners[:, 0], 0, max(w - lw, 0))
    y = np.clip(corners[:, 1], 0, max(h - lh, 0))
    return np.column_stack([x, y, x + lw, y + lh])


def _place(
    p: LocatedPart, own: Box, text: str, style: Style, size: tuple[int, int], obstacles: list[Box]
) -> tuple[Box, bool] | None:
    """(box, leader) for one label, or None where the image has no free place for it."""
    lw, lh, _ = style.box_size(text)
    w, h = size
    if lw > w or lh > h:
        return None
    beside = _around(own, lw, lh, style.gap, size)
    centre = np.array([(own[0] + own[2]) / 2, (own[1] + own[3]) / 2])
    reach = 8 * lh + max(own[2] - own[0], own[3] - own[1])
    clear_of_own = [*obstacles, own]
    ok = np.flatnonzero(_free(beside, clear_of_own))
    if ok.size:  # beside the part
        return _box(beside[ok[0]]), False
    if (near := _nearest_free(centre, lw, lh, size, clear_of_own, reach)) is not None:  # near it, a line to it
        return near, True
    ok = np.flatnonzero(_free(beside, obstacles))
    if ok.size:  # beside it but over its edge (a part at the image's border)
        return _box(beside[ok[0]]), False
    on_part = _inside(np.array([[centre[0] - lw // 2, centre[1] - lh // 2]], dtype=int), lw, lh, size)
    if _free(on_part, obstacles)[0]:
        return _box(on_part[0]), False
    anywhere = _nearest_free(centre, lw, lh, size, obstacles, within=None)
    return None if anywhere is None else (anywhere, True)


def _nearest_free(
    centre: np.ndarray, lw: int, lh: int, size: tuple[int, int], obstacles: list[Box], within: float | None
) -> Box | None:
    """The free label box on a grid of half a label's height whose centre is nearest `centre`."""
    w, h = size
    step = max(2, lh // 2)
    xs, ys = np.arange(0, w - lw + 1, step), np.arange(0, h - lh + 1, step)
    gx, gy = np.meshgrid(xs, ys)
    corners = np.column_stack([gx.ravel(), gy.ravel()])
    dist = np.hypot(corners[:, 0] + lw / 2 - centre[0], corners[:, 1] + lh / 2 - centre[1])
    keep = np.ones(len(corners), bool) if within is None else dist <= within
    corners, dist = corners[keep], dist[keep]
    if not len(corners):
        return None
    boxes = np.column_stack([corners, corners + (lw, lh)])
    free = _free(boxes, obstacles)
    if not free.any():
        return None
    best = np.flatnonzero(free)[np.argmin(dist[free])]
    return _box(boxes[best])


def _box(row: Sequence[float] | np.ndarray) -> Box:
    return int(row[0]), int(row[1]), int(row[2]), int(row[3])


def _legend_entries(result: LocateResult, order: Sequence[int] | None) -> list[tuple[str, str]]:
    present = {p.cls for p in result.objects}
    entries: list[tuple[str, str]] = [
        (cls, text) for cls, text in (("bolt", "bolt"), ("nut", "nut"), ("unknown", "not picked")) if cls in present
    ]
    if present - {"bolt", "nut", "unknown"}:
        entries.insert(len(entries) - ("unknown" in present), ("taught", "taught type"))
    if order is None and result.objects:
        entries.append(("number", "part No."))
    elif order:
        entries.append(("number", "pick order"))
    return entries


def _place_legend(out: Layout, result: LocateResult, order: Sequence[int] | None) -> None:
    """The legend's entries in rows no wider than half the image, in the corner covering the
    least of the parts' boxes."""
    entries = _legend_entries(result, order)
    if not entries:
        return
    style, (w, h) = out.style, out.image_size
    scale = 0.8
    _, row_h, _ = style.box_size("0p", scale)
    swatch = 2 * row_h
    items, x, y, width = [], 0, 0, 0
    for kind, text in entries:
        tw, _, _ = style.box_size(text, scale)
        iw = swatch + tw
        if x and x + iw > w // 2:
            x, y = 0, y + row_h
        items.append((kind, text, (x, y, x + iw, y + row_h)))
        x += iw + style.pad
        width = max(width, x - style.pad)
    lw, lh = width + 2 * style.pad, y + row_h + 2 * style.pad
    if lw > w - 2 * style.gap or lh > h - 2 * style.gap:
        return  # no room on this image: the outlines' colours must do
    m = style.gap
    corners = [(m, m), (w - m - lw, m), (m, h - m - lh), (w - m - lw, h - m - lh)]
    boxes = list(out.part_boxes.values())

    def covered(c: tuple[int, int]) -> int:
        x0, y0 = c
        return sum(
            max(0, min(x0 + lw, b[2]) - max(x0, b[0])) * max(0, min(y0 + lh, b[3]) - max(y0, b[1])) for b in boxes
        )

    x0, y0 = min(corners, key=covered)
    out.legend_box = (x0, y0, x0 + lw, y0 + lh)
    off = (x0 + style.pad, y0 + style.pad)
    out.legend_items = [(k, t, (b[0] + off[0], b[1] + off[1], b[2] + off[0], b[3] + off[1])) for k, t, b in items]


# --- drawing ---


def _draw_part(out: np.ndarray, p: LocatedPart, style: Style) -> None:
    colour = _colour(p.cls)
    if p.outline_px is not None and len(p.outline_px):
        outline = np.asarray(p.outline_px).reshape(-1, 1, 2).astype(np.int32)
        drawn = cv2.approxPolyDP(outline, 0.35 * style.thick + 0.35, True)  # 5x fewer segments to draw, unseen
        if p.cls == "unknown":
            _dashed(out, drawn, colour, style.thick, 2 * style.text_px // 3)
        else:
            cv2.drawContours(out, [drawn], -1, colour, style.thick, cv2.LINE_AA)
    if p.cls == "unknown":
        return
    x, y = (int(round(v)) for v in p.pixel)
    cv2.drawMarker(out, (x, y), colour, cv2.MARKER_CROSS, max(6, style.text_px // 2), style.thick)
    if p.cls == "bolt" and p.outline_px is not None and len(p.outline_px) >= 2:
        _draw_jaws(out, p, style.thick)


def _dashed(
    out: np.ndarray, points: np.ndarray, colour: tuple[int, int, int], thick: int, dash_px: int, closed: bool = True
) -> None:
    """A polyline (closed: an outline) drawn as dashes of about `dash_px`."""
    pts = points.reshape(-1, 2)
    if closed:
        pts = np.concatenate([pts, pts[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    on = (s // max(dash_px, 2)).astype(int) % 2 == 0
    runs, start = [], None
    for i, flag in enumerate(on):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            runs.append(pts[start : i + 1])
            start = None
    if start is not None:
        runs.append(pts[start:])
    cv2.polylines(
        out, [r.reshape(-1, 1, 2).astype(np.int32) for r in runs if len(r) >= 2], False, colour, thick, cv2.LINE_AA
    )


def _draw_jaws(out: np.ndarray, part: LocatedPart, thick: int) -> None:
    """A line across the bolt's axis through its centre, with a bar at each end: where the jaws close."""
    points = np.asarray(part.outline_px).reshape(-1, 2).astype(np.float32)
    vx, vy = cv2.fitLine(points, cv2.DIST_L2, 0, 0.01, 0.01).ravel()[:2]
    nx, ny = -vy, vx  # across the axis
    width = np.ptp(points @ np.array([nx, ny], np.float32))
    half = 0.5 * width + 6 * thick
    c = np.array(part.pixel, np.float32)
    ends = [c + s * half * np.array([nx, ny]) for s in (-1, 1)]
    cv2.line(out, _pt(ends[0]), _pt(ends[1]), JAWS_BGR, thick, cv2.LINE_AA)
    for e in ends:
        bar = 4 * thick * np.array([vx, vy])
        cv2.line(out, _pt(e - bar), _pt(e + bar), JAWS_BGR, thick + 1, cv2.LINE_AA)


def _draw_leader(out: np.ndarray, label: PlacedLabel, part: LocatedPart, style: Style) -> None:
    """A thin line from the label's box to the part's centre."""
    x0, y0, x1, y1 = label.box_px
    cx, cy = part.pixel
    start = (int(np.clip(cx, x0, x1 - 1)), int(np.clip(cy, y0, y1 - 1)))
    cv2.line(out, start, _pt(part.pixel), _colour(label.cls), max(1, style.thick // 2), cv2.LINE_AA)


def _draw_label(out: np.ndarray, label: PlacedLabel, style: Style) -> None:
    x0, y0, x1, y1 = label.box_px
    cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), _colour(label.cls), -1)
    _, _, base = style.box_size(label.text)
    org = (x0 + style.pad, y1 - style.pad - base)
    cv2.putText(out, label.text, org, FONT, style.font_scale, _text_colour(label.cls), style.thick, cv2.LINE_AA)


def _draw_legend(out: np.ndarray, plan: Layout, style: Style) -> None:
    if plan.legend_box is None:
        return
    x0, y0, x1, y1 = plan.legend_box
    roi = out[y0:y1, x0:x1]
    cv2.addWeighted(roi, 0.3, np.full_like(roi, 30), 0.7, 0, dst=roi)  # dark, the table faintly through
    scale, thick = 0.8 * style.font_scale, max(1, style.thick - 1)
    _, base = cv2.getTextSize("0p", FONT, scale, thick)
    for kind, text, (ix0, iy0, _, iy1) in plan.legend_items:
        swatch = 2 * (iy1 - iy0)
        mid = (iy0 + iy1) // 2
        a, b = (ix0 + style.pad, mid), (ix0 + swatch - 2 * style.pad, mid)
        if kind == "number":
            r = (iy1 - iy0) // 2 - 1
            cx = (a[0] + b[0]) // 2
            cv2.rectangle(out, (cx - r, mid - r), (cx + r, mid + r), (220, 220, 220), -1)
            (tw, th), _ = cv2.getTextSize("1", FONT, 0.8 * scale, thick)
            cv2.putText(out, "1", (cx - tw // 2, mid + th // 2), FONT, 0.8 * scale, (0, 0, 0), thick, cv2.LINE_AA)
        elif kind == "unknown":
            dense = np.linspace(a, b, 16).astype(np.int32)
            _dashed(out, dense, _colour(kind), style.thick, max(2, (b[0] - a[0]) // 4), closed=False)
        else:
            cv2.line(out, a, b, _colour(kind), style.thick + 1, cv2.LINE_AA)
        org = (ix0 + swatch + style.pad, iy1 - style.pad - base)
        cv2.putText(out, text, org, FONT, scale, (255, 255, 255), thick, cv2.LINE_AA)


def _pt(v: Sequence[float] | np.ndarray) -> tuple[int, int]:
    return int(round(float(v[0]))), int(round(float(v[1])))
