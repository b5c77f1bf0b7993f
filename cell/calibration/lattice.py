"""Numbering circle centres by growing a lattice over them.

Growth starts at a seed blob and steps to neighbours predicted by the local lattice
vectors, which are updated at every step, so perspective, lens distortion and rotation
are followed; one- and two-step predictions bridge missing circles. Several seeds are
tried and the largest consistent lattice wins. The result must span exactly the
configured columns x rows, or numbering fails with what was seen: a mis-numbered
calibration is worse than none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cell.config import PlateConfig
from cell.errors import PlateNotFound
from cell.wording import plural


@dataclass
class Numbering:
    """Blob index -> (column, row), zero-based, column along the plate's X."""

    index: np.ndarray  # (M,) indices into the blob list
    col_row: np.ndarray  # (M, 2) int
    strays: np.ndarray  # blob indices not on the lattice
    missing: list[tuple[int, int]]  # lattice nodes with no blob


def _seed_basis(points: np.ndarray, near: np.ndarray, i: int) -> tuple[tuple, tuple] | None:
    """Two shortest non-parallel steps from point i to its neighbours."""
    order = near[1:9]
    if len(order) < 4:
        return None
    u = points[order[0]] - points[i]
    for j in order[1:]:
        v = points[j] - points[i]
        cos = abs(u @ v) / (np.linalg.norm(u) * np.linalg.norm(v))
        if cos < 0.5 and np.linalg.norm(v) < 2.0 * np.linalg.norm(u):
            return (float(u[0]), float(u[1])), (float(v[0]), float(v[1]))
    return None


_DIRS = ((1, 0, 1), (1, 0, 2), (-1, 0, 1), (-1, 0, 2), (0, 1, 1), (0, 1, 2), (0, -1, 1), (0, -1, 2))
_STEP_U = np.array([da * n for da, _, n in _DIRS], dtype=np.float64)  # multiples of the u vector per prediction
_STEP_V = np.array([db * n for _, db, n in _DIRS], dtype=np.float64)
_ONE_STEP = np.arange(0, 8, 2)


def _grow(points: np.ndarray, neighbours: np.ndarray, sizes, seed: int, tol: float):
    """Lattice nodes reached from `seed`, stepping by the local lattice vectors.

    A blob is taken for a node only if it is near the predicted position and, when sizes are
    given, of a similar size to the blob it was reached from (clutter rarely is both). Growth is
    breadth first, a wave at a time: a node's predictions depend only on its own lattice vectors,
    so a whole wave's are computed in one step, then taken in queue order.
    """
    basis = _seed_basis(points, neighbours[seed], seed)
    if basis is None:
        return {}, 1
    node_of = {seed: (0, 0)}
    blob_at = {(0, 0): seed}
    local = {seed: (*basis[0], *basis[1])}  # each reached blob's lattice vectors (ux, uy, vx, vy)
    xy = points.tolist()
    xs, ys = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    conflicts = 0
    wave = [seed]
    while wave:
        idx = np.array(wave)
        uv = np.array([local[p] for p in wave])
        u, v = uv[:, :2], uv[:, 2:]
        reach2 = tol**2 * np.minimum((u * u).sum(axis=1), (v * v).sum(axis=1))
        cand = neighbours[idx]  # (k, m)
        # Per coordinate: the eight predictions (k, 8) against the neighbours (k, m), contiguous.
        dx = xs[cand][:, None, :] - (xs[idx][:, None] + _STEP_U * u[:, :1] + _STEP_V * v[:, :1])[:, :, None]
        dy = ys[cand][:, None, :] - (ys[idx][:, None] + _STEP_U * u[:, 1:] + _STEP_V * v[:, 1:])[:, :, None]
        dist2 = dx * dx + dy * dy  # (k, 8, m)
        best = dist2.argmin(axis=2)
        rows = np.arange(len(wave))[:, None]
        nearest = cand[rows, best]
        usable = dist2[rows, np.arange(8)[None, :], best] <= reach2[:, None]
        if sizes is not None:
            ratio = sizes[nearest] / sizes[idx][:, None]
            usable &= (ratio > 0.67) & (ratio < 1.5)
        # Per direction: one step, else two steps (bridging a gap); -1 where neither is usable.
        take = np.where(usable[:, 0::2], _ONE_STEP, np.where(usable[:, 1::2], _ONE_STEP + 1, -1))
        nearest_list, take_list = nearest.tolist(), take.tolist()
        following = []
        for w, p in enumerate(wave):
            a, b = node_of[p]
            px, py = xy[p]
            for k in take_list[w]:
                if k < 0:
                    continue
                da, db, n = _DIRS[k]
                j = nearest_list[w][k]
                node = (a + n * da, b + n * db)
                if j in node_of:
                    if node_of[j] != node:
                        conflicts += 1
                    continue
                if node in blob_at:
                    conflicts += 1
                    continue
                node_of[j] = node
                blob_at[node] = j
                step = n * (da + db)
                ox, oy = (xy[j][0] - px) / step, (xy[j][1] - py) / step
                local[j] = (ox, oy, *local[p][2:]) if db == 0 else (*local[p][:2], ox, oy)
                following.append(j)
        wave = following
    return node_of, conflicts


def _neighbours(points: np.ndarray, k: int) -> np.ndarray:
    """Each point's k nearest (itself first)."""
    x, y = points[:, 0], points[:, 1]
    dist2 = (x[:, None] - x[None, :]) ** 2 + (y[:, None] - y[None, :]) ** 2
    k = min(len(points), k)
    near = np.argpartition(dist2, k - 1, axis=1)[:, :k]
    rows = np.arange(len(points))[:, None]
    return near[rows, dist2[rows, near].argsort(axis=1)]


def number_lattice(
    points: np.ndarray, plate: PlateConfig, tol: float, max_missing: int = 10, sizes: np.ndarray | None = None
) -> Numbering:
    """Give each blob centre its (column, row) on the plate, or fail saying what was seen.

    `sizes` (blob diameters), when given, keep blobs of very different sizes off one lattice.
    """
    n = len(points)
    if n < 4:
        raise PlateNotFound(f"found {plural(n, 'blob')}, too few for a {plate.columns} x {plate.rows} plate")
    # Seeds: blobs nearest the middle of the crowd first, then spread through the list.
    centre = np.median(points, axis=0)
    order = np.argsort(np.hypot(*(points - centre).T))
    seeds = list(order[:12]) + list(order[12 :: max(1, n // 12)])
    # Steps of one or two pitches stay within a point's 24 nearest neighbours.
    neighbours = _neighbours(points, 25)
    size_list = None if sizes is None else np.asarray(sizes, dtype=np.float64)
    best: dict[int, tuple[int, int]] = {}
    covered: set[int] = set()
    for s in seeds:
        if int(s) in covered:
            continue  # a seed on a lattice already grown would grow the same one again
        grown, conflicts = _grow(points, neighbours, size_list, int(s), tol)
        if conflicts:
            continue
        covered.update(grown)
        if len(grown) > len(best):
            best = grown
            ab = np.array(list(grown.values()))
            if sorted(ab.max(axis=0) - ab.min(axis=0) + 1) == sorted((plate.columns, plate.rows)):
                break  # the whole plate: other seeds would grow the same lattice
    if not best:
        raise PlateNotFound(f"found {plural(n, 'blob')}, none form a consistent lattice")
    idx = np.array(list(best.keys()))
    ab = np.array([best[i] for i in idx])
    ab -= ab.min(axis=0)
    keep = _plate_window(ab, plate)
    idx, ab = idx[keep], ab[keep] - ab[keep].min(axis=0)
    extent = ab.max(axis=0) + 1
    col_row = _orient(points[idx], ab, extent, plate)
    ext = col_row.max(axis=0) + 1
    fit = f"found {plural(n, 'blob')}, {len(idx)} fit a {ext[0]} x {ext[1]} lattice"
    if tuple(ext) != (plate.columns, plate.rows):
        raise PlateNotFound(
            f"{fit}, expected {plate.columns} x {plate.rows}"
            + _missing_lines(col_row, plate)
            + " (is the whole plate in view, and does the config's plate match it?)"
        )
    occupied = {tuple(cr) for cr in col_row}
    missing = [(c, r) for r in range(plate.rows) for c in range(plate.columns) if (c, r) not in occupied]
    if len(missing) > max_missing:
        raise PlateNotFound(f"{fit} with {len(missing)} circles missing (at most {max_missing} allowed)")
    stray = np.ones(n, bool)
    stray[idx] = False
    strays = np.flatnonzero(stray)
    return Numbering(idx, col_row, strays, missing)


def _plate_window(ab: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """Which grown nodes to keep: all of them, or, when the lattice ran past the plate onto
    blobs that happen to line up with it (print, letters), the plate-sized window holding the
    most nodes, if exactly one does."""
    extent = ab.max(axis=0) + 1
    sizes = {(plate.columns, plate.rows), (plate.rows, plate.columns)}
    if not any(extent[0] > w or extent[1] > h for w, h in sizes) or not any(
        extent[0] >= w and extent[1] >= h for w, h in sizes
    ):
        return np.ones(len(ab), bool)
    counts = {}
    for w, h in sizes:
        for a in range(extent[0] - w + 1):
            for b in range(extent[1] - h + 1):
                inside = (ab[:, 0] >= a) & (ab[:, 0] < a + w) & (ab[:, 1] >= b) & (ab[:, 1] < b + h)
                counts[(a, b, w, h)] = inside
    ranked = sorted(counts.values(), key=np.count_nonzero, reverse=True)
    if len(ranked) > 1 and np.count_nonzero(ranked[0]) == np.count_nonzero(ranked[1]):
        return np.ones(len(ab), bool)  # no single best place: report the whole lattice
    return ranked[0]


def _missing_lines(col_row: np.ndarray, plate: PlateConfig) -> str:
    cols, rows = col_row.max(axis=0) + 1
    notes = []
    if rows < plate.rows:
        notes.append(f"{plate.rows - rows} row(s) missing")
    if cols < plate.columns:
        notes.append(f"{plate.columns - cols} column(s) missing")
    if rows > plate.rows or cols > plate.columns:
        notes.append("more rows or columns than the plate has")
    return ", " + ", ".join(notes) if notes else ""


def _orient(pts: np.ndarray, ab: np.ndarray, extent: np.ndarray, plate: PlateConfig) -> np.ndarray:
    """Map grown lattice indices (a, b) to plate (column, row) with point 1 at the configured corner."""
    # Mean image step along each lattice index, by least squares pts ~ a*sa + b*sb + o.
    A = np.column_stack([ab, np.ones(len(ab))])
    sol, *_ = np.linalg.lstsq(A, pts, rcond=None)
    sa, sb = sol[0], sol[1]
    la, lb = np.linalg.norm(sa), np.linalg.norm(sb)
    ratio = plate.pitch_x_mm / plate.pitch_y_mm
    if abs(np.log(ratio)) > 0.05:
        # Distinct pitches: the longer image step is the longer pitch.
        a_is_x = (la > lb) == (ratio > 1)
    elif plate.columns != plate.rows and sorted(extent) == sorted((plate.columns, plate.rows)):
        a_is_x = extent[0] == plate.columns
    else:
        # Symmetric plate: X is the lattice direction nearest the image's x axis.
        a_is_x = abs(sa[0]) / la >= abs(sb[0]) / lb
    cr = ab.copy() if a_is_x else ab[:, ::-1].copy()
    sx, sy = (sa, sb) if a_is_x else (sb, sa)
    # Signs: columns run left-to-right from a left corner, rows top-to-bottom from a top one.
    want_x = -1.0 if plate.first_point.endswith("right") else 1.0
    want_y = -1.0 if plate.first_point.startswith("bottom") else 1.0
    # A rotated plate: decide by the axis's image direction (valid for rotations below 45 deg).
    if np.sign(sx[0]) != want_x:
        cr[:, 0] = cr[:, 0].max() - cr[:, 0]
    if np.sign(sy[1]) != want_y:
        cr[:, 1] = cr[:, 1].max() - cr[:, 1]
    return cr
