"""Teaching a part type from frames: the one path `run-cell part teach` and the screen's Teach page
share. Each frame shows one or more examples of the part alone on the backlit table; every blob
large enough to be a part is an example (`silhouettes`), its footprint corrected for the part's
height through the calibration's camera pose; `cell.vision.shapes.teach` makes the model or
refuses in words (TeachRefused: the examples disagree, touch, leave the image, cannot be gripped).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from cell.core.parts import BUILT_IN_PARTS, NAME_PATTERN
from cell.errors import InputError
from cell.vision.config import PartsConfig
from cell.vision.locate import silhouettes
from cell.vision.shapes import Example, ShapeModel, TeachReport, teach

MAX_HEIGHT_MM = 200.0  # as a recipe's types.NAME.height_mm allows


def check_type_name(name: str) -> str:
    """A taught type's name as recipes and counters take it (never a path), or InputError."""
    if not isinstance(name, str) or not NAME_PATTERN.match(name) or name in BUILT_IN_PARTS or name == "unknown":
        raise InputError(
            f"part type name {name!r} not allowed",
            hint="1-32 lower-case letters, digits, - and _, starting with a letter; not bolt, nut or unknown",
        )
    return name


def check_height_mm(height_mm: float) -> float:
    """The part's height lying on the table: more than 0, at most MAX_HEIGHT_MM, or InputError."""
    if not (isinstance(height_mm, int | float) and 0 < height_mm <= MAX_HEIGHT_MM):
        raise InputError(f"height {height_mm!r} mm: the part's height, more than 0 and at most {MAX_HEIGHT_MM:g} mm")
    return float(height_mm)


def camera_centre(mapper, parts: PartsConfig) -> np.ndarray | None:
    """Where the camera is (table mm), for the height correction; None without a pose or when it is off."""
    camera = getattr(mapper, "camera", None)
    return camera.center_table_mm if camera is not None and parts.use_height_correction else None


def examples_in(image: np.ndarray, mapper, parts: PartsConfig, height_mm: float, label: str) -> list[Example]:
    """Every part seen in one frame as an example, named "`label` part N"; InputError when none is seen."""
    found = silhouettes(image, mapper, parts)
    if not found:
        raise InputError(f"{label}: no part seen", hint="the part alone on the backlit table, dark against it")
    centre = camera_centre(mapper, parts)
    return [
        Example.of(sil, height_mm, centre, f"{label} part {i}", border)
        for i, (sil, border, _) in enumerate(found, start=1)
    ]


def teach_examples(name: str, examples: Sequence[Example], height_mm: float, parts: PartsConfig) -> TeachReport:
    """The model from the examples with the config's jaws (TeachRefused saying why not)."""
    return teach(
        name,
        examples,
        height_mm,
        max_opening_mm=parts.jaw_max_opening_mm,
        jaw_face_mm=parts.jaw_face_width_mm,
        clearance_mm=parts.jaw_clearance_mm,
    )


# ---- the picture: each example's outline and, with a model, where its jaws close ----------------


def table_to_pixel(mapper, points_mm: np.ndarray, height_mm: float, image_size: tuple[int, int]) -> np.ndarray:
    """The pixels (N, 2) where points on the plane `height_mm` above the table are seen: the mapper's
    pixel_to_table_mm inverted (an affine guess from a grid over the image, then Newton steps)."""
    pts = np.asarray(points_mm, np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return pts
    if getattr(mapper, "camera", None) is None:
        height_mm = 0.0  # a plain scale knows no height
    w, h = image_size
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    grid_px = np.column_stack([gx.ravel(), gy.ravel()])
    grid_mm = np.asarray(mapper.pixel_to_table_mm(grid_px, height_mm)).reshape(-1, 2)
    design = np.column_stack([grid_mm, np.ones(len(grid_mm))])
    affine, *_ = np.linalg.lstsq(design, grid_px, rcond=None)
    px = np.column_stack([pts, np.ones(len(pts))]) @ affine
    for _ in range(4):
        probes = np.concatenate([px, px + (1.0, 0.0), px + (0.0, 1.0)])
        q = np.asarray(mapper.pixel_to_table_mm(probes, height_mm)).reshape(3, -1, 2)
        ju, jv = q[1] - q[0], q[2] - q[0]  # table mm per pixel along x and y
        r = pts - q[0]
        det = ju[:, 0] * jv[:, 1] - ju[:, 1] * jv[:, 0]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        du = (r[:, 0] * jv[:, 1] - r[:, 1] * jv[:, 0]) / det
        dv = (ju[:, 0] * r[:, 1] - ju[:, 1] * r[:, 0]) / det
        px = px + np.column_stack([du, dv])
    return px


OUTLINE_BGR = (170, 60, 150)  # a taught type's colour (cell.vision.annotate.TAUGHT_BGR)
REFUSED_BGR = (40, 40, 220)
JAWS_BGR = (255, 80, 0)


def draw_examples(
    image: np.ndarray,
    mapper,
    examples: Sequence[Example],
    model: ShapeModel | None,
    parts: PartsConfig,
    crop: bool = False,
) -> np.ndarray:
    """The frame with each example's outline (its silhouette as the camera saw it), its number, and, with a
    model, the jaws where they would close on it (each jaw `jaw_thickness_mm` deep, `jaw_face_width_mm` wide,
    either side of the grip point at the model's opening, drawn at half the part's height). With `crop`, only
    the part of the frame around the examples (a margin of a fifth of the frame's height about them)."""
    out = np.ascontiguousarray(image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)).copy()
    h, w = out.shape[:2]
    size = (w, h)
    thick = max(1, round(min(w, h) / 400))
    scale = max(0.5, min(w, h) / 900)
    colour = OUTLINE_BGR if model is not None else REFUSED_BGR
    seen: list[np.ndarray] = []
    for k, example in enumerate(examples, start=1):
        outer, holes = example.silhouette
        for poly in (outer, *holes):
            ring = table_to_pixel(mapper, poly, 0.0, size)
            cv2.polylines(out, [np.rint(ring).astype(np.int32).reshape(-1, 1, 2)], True, colour, thick, cv2.LINE_AA)
        if model is not None:
            _draw_jaws(out, mapper, example, model, parts, size, thick)
        top = table_to_pixel(mapper, outer, 0.0, size)
        seen.append(top)
        x, y = int(top[:, 0].max()) + 4 * thick, int(top[:, 1].min())
        label = str(k)
        (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, thick + 1)
        x, y = min(max(x, 0), w - tw - 4), min(max(y, th + 4), h - base - 2)
        cv2.rectangle(out, (x - 2, y - th - 2), (x + tw + 2, y + base), colour, -1)
        cv2.putText(out, label, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick + 1, cv2.LINE_AA)
    if crop and seen:
        pts = np.vstack(seen)
        margin = h / 5
        x0, y0 = (max(0, int(v - margin)) for v in pts.min(axis=0))
        x1, y1 = int(min(w, pts[:, 0].max() + margin)), int(min(h, pts[:, 1].max() + margin))
        if x1 - x0 >= 16 and y1 - y0 >= 16:
            out = out[y0:y1, x0:x1].copy()
    return out


def example_fit(model: ShapeModel, example: Example) -> tuple[np.ndarray, float, float, float]:
    """Where the model lies on an example (centre, table mm; angle, deg) and how well it fits it (misfit mm2,
    score 0-1): what the finder will measure."""
    match = model.match(example.footprint, example.silhouette, example.camera_centre)
    return match.centre_mm, match.angle_deg, match.misfit_mm2, match.score


def _draw_jaws(
    out: np.ndarray,
    mapper,
    example: Example,
    model: ShapeModel,
    parts: PartsConfig,
    size: tuple[int, int],
    thick: int,
) -> None:
    centre, angle, _, _ = example_fit(model, example)
    grasp, jaw_deg = model.grip_on_table(centre, angle)
    a = math.radians(jaw_deg)
    d, side = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    half, t, fw = model.grip.opening_mm / 2, parts.jaw_thickness_mm, parts.jaw_face_width_mm / 2
    z = model.height_mm / 2
    ends = []
    for sign in (1.0, -1.0):
        near, far = grasp + sign * half * d, grasp + sign * (half + t) * d
        jaw = np.array([near - fw * side, far - fw * side, far + fw * side, near + fw * side])
        poly = np.rint(table_to_pixel(mapper, jaw, z, size)).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(out, [poly], JAWS_BGR, cv2.LINE_AA)
        ends.append(near)
    line = table_to_pixel(mapper, np.array(ends), z, size)
    cv2.line(out, _pt(line[0]), _pt(line[1]), JAWS_BGR, thick, cv2.LINE_AA)
    g = table_to_pixel(mapper, np.array([grasp]), z, size)[0]
    cv2.drawMarker(out, _pt(g), JAWS_BGR, cv2.MARKER_CROSS, 6 * thick, thick)


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))
