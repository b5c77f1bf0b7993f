"""Drawing what the vision found on a frame: the operator's picture of the table (the paper's
Fig. 6), shared by `run-cell locate --annotate` and the operator screen."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from cell.vision.types import LocateResult

_COLOURS_BGR = {"bolt": (0, 140, 255), "nut": (0, 180, 0), "unknown": (0, 0, 230)}


def annotate(image: np.ndarray, result: LocateResult, order: Sequence[int] | None = None) -> np.ndarray:
    """The image with each part outlined, numbered and labelled (the paper's Fig. 6): bolts with
    the line the jaws close along, unknown parts with the reason they are left. `order` (part
    ids in the order the cell will pick them) puts a badge 1, 2, 3... beside those parts."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = max(out.shape[1] / 1280, 0.6)
    thick = max(1, round(2 * scale))
    rank = {part_id: n for n, part_id in enumerate(order or (), start=1)}
    for p in result.objects:
        colour = _COLOURS_BGR[p.cls]
        if p.outline_px is not None:
            cv2.drawContours(out, [p.outline_px], -1, colour, thick, cv2.LINE_AA)
        x, y = (int(round(v)) for v in p.pixel)
        cv2.drawMarker(out, (x, y), colour, cv2.MARKER_CROSS, max(6, round(12 * scale)), thick)
        if p.cls == "bolt" and p.outline_px is not None:
            _draw_jaws(out, p, thick)
        label = f"{p.id} {p.cls}" + (f": {_short(p.reason)}" if p.cls == "unknown" else "")  # red: never picked
        org = (x + round(8 * scale), y - round(8 * scale))
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (255, 255, 255), thick + 2, cv2.LINE_AA)
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, colour, thick, cv2.LINE_AA)
        if p.id in rank:
            _draw_rank(out, (x, y), rank[p.id], scale, thick)
    return out


def _draw_rank(out: np.ndarray, centre: tuple[int, int], n: int, scale: float, thick: int) -> None:
    """The pick order as a white disc with a black number, up and left of the part's centre."""
    r = round(13 * scale)
    c = (centre[0] - round(1.6 * r), centre[1] - round(1.6 * r))
    cv2.circle(out, c, r, (255, 255, 255), -1, cv2.LINE_AA)
    cv2.circle(out, c, r, (0, 0, 0), max(1, thick // 2), cv2.LINE_AA)
    text = str(n)
    size = 0.55 * scale if n < 10 else 0.42 * scale
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, size, thick)
    org = (c[0] - w // 2, c[1] + h // 2)
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, size, (0, 0, 0), thick, cv2.LINE_AA)


def _draw_jaws(out: np.ndarray, part, thick: int) -> None:
    """A line across the bolt's axis through its centre, with a bar at each end: where the jaws close."""
    points = part.outline_px.reshape(-1, 2).astype(np.float32)
    vx, vy = cv2.fitLine(points, cv2.DIST_L2, 0, 0.01, 0.01).ravel()[:2]
    nx, ny = -vy, vx  # across the axis
    width = np.ptp(points @ np.array([nx, ny], np.float32))
    half = 0.5 * width + 6 * thick
    c = np.array(part.pixel, np.float32)
    ends = [c + s * half * np.array([nx, ny]) for s in (-1, 1)]
    colour = (255, 80, 0)
    cv2.line(out, _pt(ends[0]), _pt(ends[1]), colour, thick, cv2.LINE_AA)
    for e in ends:
        bar = 4 * thick * np.array([vx, vy])
        cv2.line(out, _pt(e - bar), _pt(e + bar), colour, thick + 1, cv2.LINE_AA)


def _pt(v) -> tuple[int, int]:
    return int(round(float(v[0]))), int(round(float(v[1])))


def _short(text: str, limit: int = 48) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
