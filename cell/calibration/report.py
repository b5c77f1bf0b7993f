"""The calibration report: the paper's Table III for every point, its summary lines, and
the files an integrator keeps (CSV, the numbered plate image of Fig. 4, the deviation plot
of Fig. 5)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import cv2
import numpy as np

from cell.atomicfile import ensure_folder, write_bytes_atomic, write_text_atomic
from cell.calibration.pipeline import CalibrationResult
from cell.calibration.store import HEIGHT_DOUBT_SDS
from cell.imageio import write_image_atomic
from cell.wording import plural


def table3_rows(result: CalibrationResult) -> list[dict]:
    """Calibrated X/Y, original X/Y, deviation = original - calibrated, per point found."""
    rows = []
    for num, px, cal, orig in zip(
        result.points.number, result.points.pixel, result.calibrated_mm, result.points.table_mm, strict=True
    ):
        rows.append(
            {
                "point": int(num),
                "x_px": float(px[0]),
                "y_px": float(px[1]),
                "X_cal_mm": float(cal[0]),
                "Y_cal_mm": float(cal[1]),
                "X_mm": float(orig[0]),
                "Y_mm": float(orig[1]),
                "dX_mm": float(orig[0] - cal[0]),
                "dY_mm": float(orig[1] - cal[1]),
            }
        )
    return rows


FIELDS = ["point", "x_px", "y_px", "X_cal_mm", "Y_cal_mm", "X_mm", "Y_mm", "dX_mm", "dY_mm"]


def missing_rows(result: CalibrationResult) -> list[dict]:
    """Points not found on the image: their plate position, nothing measured."""
    pattern = result.calibration.pattern
    cols = int(pattern["columns"])
    rows = []
    for num in result.points.missing:
        c, r = (int(num) - 1) % cols, (int(num) - 1) // cols
        rows.append(
            {"point": int(num), "X_mm": c * float(pattern["pitch_x_mm"]), "Y_mm": r * float(pattern["pitch_y_mm"])}
        )
    return rows


def write_csv(result: CalibrationResult, path: Path) -> None:
    """Every plate point in number order; a missing one has its plate position and empty measurements."""
    rows = sorted(table3_rows(result) + missing_rows(result), key=lambda r: r["point"])
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=FIELDS, restval="")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{v:.6f}" if isinstance(v, float) else v) for k, v in r.items()})
    write_text_atomic(path, buf.getvalue())


def _plausibility_lines(result: CalibrationResult) -> list[str]:
    """What the plausibility gates measured: the pitch ratio the circles see, the camera height the
    plate alone gives and how surely (part-height correction needs it)."""
    lines = []
    if result.pitch_ratio is not None:
        p = result.calibration.pattern
        configured = p["pitch_x_mm"] / p["pitch_y_mm"]
        lines.append(
            f"pitch ratio the circles see: {configured / result.pitch_ratio.factor:.4f} +- "
            f"{configured / result.pitch_ratio.factor * result.pitch_ratio.log_sd:.4f} (configured {configured:.4f}, "
            f"{result.pitch_ratio.circles} circles, one standard error)"
        )
    if result.plate_height_mm is not None:
        height, sd = result.plate_height_mm, result.plate_height_sd_mm
        lines.append(f"camera height from the plate alone: {height:.1f} +- {sd:.1f} mm (one standard deviation)")
        if result.raised is not None:
            r = result.raised
            lines.append(
                f"camera height from the plate raised on the {r.spacer_mm:g} mm spacer: {r.height_mm:.1f} +- "
                f"{r.sd_mm:.1f} mm ({r.points} circles, scale {r.scale:.5f}, residual {r.residual_rms_mm:.3f} mm RMS)"
            )
            used = result.calibration.camera_center_table_mm
            if used is not None:
                lines.append(f"camera height used: {used[2]:.1f} mm")
    cost = result.calibration.statistics.get("camera_height", {}).get("cost")
    if isinstance(cost, dict) and isinstance(cost.get("worst_mm"), int | float):
        lines.append(
            f"what the height's doubt costs: a {cost['part_height_mm']:.1f} mm high part's centre off by up to "
            f"{cost['worst_mm']:.3f} mm in the field (height {cost['height_error_mm']:.1f} mm off, "
            f"{HEIGHT_DOUBT_SDS:g} standard deviations; calibration.max_height_cost_mm {cost['max_mm']:g})"
        )
    doubt = result.calibration.height_doubt()  # the height used, from everything that knew it
    if doubt is not None:
        lines.append(f"  {doubt[0]} (hint: {doubt[1]})")
    return lines


def summary_text(result: CalibrationResult, table: bool = True) -> str:
    """What the operator reads: model choice, fit and cross-validated figures, Table III."""
    cal, pts = result.calibration, result.points
    fit, cv = result.chosen.fit, result.chosen.cv
    lines = [
        f"plate: {plural(len(pts.pixel), 'circle')} numbered ({plural(pts.blobs_found, 'blob')} found, "
        f"{plural(pts.strays, 'stray')} ignored, missing: {pts.missing or 'none'})",
        f"image: {cal.image_size[0]} x {cal.image_size[1]} px",
        f"model: {result.why}",
        "",
        f"{'model':<24}{'fit RMS X':>11}{'fit RMS Y':>11}{'fit max':>9}{'CV RMS':>9}{'CV max':>9}  (mm)",
    ]
    for s in result.scores:
        mark = "*" if s is result.chosen else " "
        lines.append(
            f"{mark}{s.label:<23}{s.fit.rms_x_mm:>11.4f}{s.fit.rms_y_mm:>11.4f}"
            f"{s.fit.max_mm:>9.4f}{s.cv.rms_mm:>9.4f}{s.cv.max_mm:>9.4f}"
        )
    lines += [
        "",
        "deviation (original - calibrated), chosen model:",
        f"  fitted points:     max +dX {fit.max_pos_x_mm:+.4f}  max -dX {fit.max_neg_x_mm:+.4f}  "
        f"max +dY {fit.max_pos_y_mm:+.4f}  max -dY {fit.max_neg_y_mm:+.4f}  "
        f"RMS X {fit.rms_x_mm:.4f}  RMS Y {fit.rms_y_mm:.4f}",
        f"  cross-validated:   max +dX {cv.max_pos_x_mm:+.4f}  max -dX {cv.max_neg_x_mm:+.4f}  "
        f"max +dY {cv.max_pos_y_mm:+.4f}  max -dY {cv.max_neg_y_mm:+.4f}  "
        f"RMS X {cv.rms_x_mm:.4f}  RMS Y {cv.rms_y_mm:.4f}",
        "  (trust the cross-validated line: each point there was predicted by a fit made without it)",
    ]
    if cal.camera is not None:
        C = cal.camera.center_table_mm
        lines.append(f"camera centre (table frame): X {C[0]:.1f} mm, Y {C[1]:.1f} mm, {C[2]:.1f} mm above the table")
    lines += _plausibility_lines(result)
    lines.append(
        f"time: detect+number {result.timings_ms['detect_number_ms']:.1f} ms, "
        f"fit+cross-validate {result.timings_ms['fit_cv_ms']:.1f} ms, checks {result.timings_ms.get('checks_ms', 0.0):.1f} ms"
    )
    if table:
        lines += [
            "",
            "Table III (all points):",
            f"{'point':>5}{'X cal':>11}{'Y cal':>11}{'X':>9}{'Y':>9}{'dX':>9}{'dY':>9}",
        ]
        for r in sorted(table3_rows(result) + missing_rows(result), key=lambda r: r["point"]):
            if "X_cal_mm" not in r:
                lines.append(f"{r['point']:>5}{'not found':>22}{r['X_mm']:>9.1f}{r['Y_mm']:>9.1f}")
                continue
            lines.append(
                f"{r['point']:>5}{r['X_cal_mm']:>11.4f}{r['Y_cal_mm']:>11.4f}{r['X_mm']:>9.1f}"
                f"{r['Y_mm']:>9.1f}{r['dX_mm']:>9.4f}{r['dY_mm']:>9.4f}"
            )
    return "\n".join(lines)


def annotate_plate(image: np.ndarray, result: CalibrationResult) -> np.ndarray:
    """Every centre marked and numbered (the paper's Fig. 4); a missing point ringed where the
    fitted camera puts it, its number followed by '?'."""
    out = image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = max(0.35, out.shape[1] / 3000)
    for num, (x, y) in zip(result.points.number, result.points.pixel, strict=True):
        c = (int(round(x)), int(round(y)))
        cv2.drawMarker(out, c, (0, 0, 255), cv2.MARKER_CROSS, 12, 1, cv2.LINE_AA)
        cv2.putText(out, str(num), (c[0] + 4, c[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 160, 0), 1, cv2.LINE_AA)
    camera = result.calibration.camera
    missing = missing_rows(result)
    if camera is not None and missing:
        where = camera.project(np.array([[r["X_mm"], r["Y_mm"]] for r in missing]))
        for r, (x, y) in zip(missing, where, strict=True):
            if not (np.isfinite(x) and np.isfinite(y)):
                continue
            c = (int(round(x)), int(round(y)))
            cv2.circle(out, c, 8, (0, 0, 255), 1, cv2.LINE_AA)
            cv2.putText(
                out,
                f"{r['point']}?",
                (c[0] + 4, c[1] - 4),
                cv2.FONT_HERSHEY_SIMPLEX,
                scale,
                (0, 0, 255),
                1,
                cv2.LINE_AA,
            )
    return out


def deviation_plot(result: CalibrationResult, path: Path) -> None:
    """The deviation plot (the paper's Fig. 5) as a PNG file, written atomically."""
    write_bytes_atomic(path, deviation_png(result))


def deviation_png(result: CalibrationResult) -> bytes:
    """dX and dY per point, and the error vectors over the plate (the paper's Fig. 5), PNG bytes."""
    import matplotlib  # lazily: only a written report needs it (slow to import), and Agg goes before pyplot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = table3_rows(result)
    num = [r["point"] for r in rows]
    dx = np.array([r["dX_mm"] for r in rows])
    dy = np.array([r["dY_mm"] for r in rows])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(14, 5))
    ax1.plot(num, dx, ".-", label="dX (mm)")
    ax1.plot(num, dy, ".-", label="dY (mm)")
    ax1.axhline(0, color="k", lw=0.5)
    ax1.set_xlabel("point")
    ax1.set_ylabel("deviation = original - calibrated (mm)")
    ax1.set_title(f"{result.chosen.label}: deviation per point")
    ax1.legend()
    X = np.array([r["X_mm"] for r in rows])
    Y = np.array([r["Y_mm"] for r in rows])
    mag = np.hypot(dx, dy)
    q = ax2.quiver(X, Y, dx, dy, mag, angles="xy", cmap="viridis")
    fig.colorbar(q, ax=ax2, label="|deviation| (mm)")
    ax2.set_aspect("equal")
    ax2.invert_yaxis()
    ax2.set_xlabel("X (mm)")
    ax2.set_ylabel("Y (mm)")
    ax2.set_title(f"error vectors (max {mag.max():.4f} mm, arrows not to scale)")
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=90)
    finally:
        plt.close(fig)
    return buf.getvalue()


def write_report(image: np.ndarray, result: CalibrationResult, report_dir: Path) -> list[Path]:
    """All report files into `report_dir`; returns their paths."""
    ensure_folder(report_dir)
    paths = [
        report_dir / "table3.csv",
        report_dir / "plate_numbered.png",
        report_dir / "deviation.png",
        report_dir / "report.txt",
    ]
    write_csv(result, paths[0])
    write_image_atomic(paths[1], annotate_plate(image, result))
    deviation_plot(result, paths[2])
    write_text_atomic(paths[3], summary_text(result) + "\n")
    return paths
