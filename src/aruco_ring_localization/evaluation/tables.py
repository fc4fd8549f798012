"""The paper's Table I (errors in position) and Table II (errors in orientation), markdown and CSV.

Rows are :class:`stops.StopError`; errors are signed, estimate minus reference, in the axes of
the frame the rows are expressed in, which every title states (the demo's tables are in the lab
frame, the frame of its figures). The paper's own values (§III, gmapping against the proposed
system) are here too, so reports can put them beside ours.
"""
from __future__ import annotations

import csv
import io
import os
from typing import Dict, Sequence, Tuple

import numpy as np

from ..fileio import atomic_write_text
from .stops import StopError, summarize
from .trajectories import PoseErrors

# Paper §III, Table I: |x|, |y| and Euclidean error (cm) at the 15 positions, and Table II: the
# yaw error (deg) at the 8 orientations; both measured against gmapping, not a ground truth.
PAPER_TABLE1_CM: Tuple[Tuple[float, float, float], ...] = (
    (2.015, 4.969, 5.363), (1.255, 1.480, 1.941), (0.499, 3.132, 3.172), (2.521, 1.812, 3.104),
    (0.302, 0.221, 0.374), (2.870, 0.609, 2.932), (7.425, 1.556, 7.587), (0.257, 0.652, 0.701),
    (2.01, 2.061, 2.881), (6.611, 2.452, 7.051), (16.135, 6.152, 17.268), (3.899, 2.478, 4.619),
    (0.144, 1.468, 1.475), (1.346, 0.461, 1.423), (11.463, 5.827, 12.859))
PAPER_TABLE2_DEG: Tuple[float, ...] = (0.076, -4.501, 0.490, 1.359, -3.435, -3.169, 1.157, 1.028)
PAPER_REFERENCE = "gmapping"


def paper_statistics() -> Dict[str, float]:
    """The paper's summary figures, from its tables: position median/max (cm), |yaw| mean/max (deg)."""
    d = np.array([row[2] for row in PAPER_TABLE1_CM])
    y = np.abs(np.array(PAPER_TABLE2_DEG))
    return {"position_cm_median": float(np.median(d)), "position_cm_max": float(d.max()),
            "yaw_deg_mean_abs": float(y.mean()), "yaw_deg_max_abs": float(y.max())}


def _markdown(heading: str, columns: Sequence[str], body: Sequence[str], footer: str) -> str:
    lines = [heading, "", "| " + " | ".join(columns) + " |", "|" + "---:|" * len(columns)] + list(body)
    return "\n".join(lines + (["", footer] if footer else [])) + "\n"


def position_table_markdown(rows: Sequence[StopError], title: str = "Table I. Errors in position",
                            reference_name: str = "reference", frame: str = "the reference's frame") -> str:
    """The paper's Table I: signed x, y and the Euclidean error per position (cm), plus statistics.

    ``frame`` names the coordinates of x and y (e.g. "lab frame: x, y as in the figures").
    """
    body = []
    for r in rows:
        dx, dy, d, _ = r.errors
        body.append(f"| {r.label} | {100 * dx:+.3f} | {100 * dy:+.3f} | {100 * d:.3f} | {r.ref[0]:.3f}, {r.ref[1]:.3f} |")
    s = summarize(rows)
    footer = (f"Median Euclidean error {s['position_cm_median']:.3f} cm, mean {s['position_cm_mean']:.3f} cm, "
              f"max {s['position_cm_max']:.3f} cm over {s['n']} positions.") if s.get("n") else ""
    return _markdown(f"**{title}** (estimate - {reference_name}, cm; x, y in the {frame})",
                     ("Position", "X error (cm)", "Y error (cm)", "Euclidean error (cm)", "Reference x, y (m)"),
                     body, footer)


def orientation_table_markdown(rows: Sequence[StopError], title: str = "Table II. Errors in orientation",
                               reference_name: str = "reference", frame: str = "the reference's frame") -> str:
    """The paper's Table II: signed yaw error per orientation (deg), plus statistics."""
    body = [f"| {r.label} | {np.degrees(r.ref[2]):.2f} | {np.degrees(r.est[2]):.2f} | {np.degrees(r.errors[3]):+.3f} |"
            for r in rows]
    s = summarize(rows)
    footer = (f"Mean |error| {s['yaw_deg_mean_abs']:.3f} deg, max |error| {s['yaw_deg_max_abs']:.3f} deg "
              f"over {s['n']} orientations.") if s.get("n") else ""
    return _markdown(f"**{title}** (estimate - {reference_name}, degrees; yaw in the {frame})",
                     ("Orientation", "Reference yaw (deg)", "Estimated yaw (deg)", "Error (deg)"), body, footer)


CSV_COLUMNS = ("label", "start_s", "end_s", "n", "ref_x_m", "ref_y_m", "ref_yaw_deg", "est_x_m", "est_y_m",
               "est_yaw_deg", "err_x_cm", "err_y_cm", "err_euclidean_cm", "err_yaw_deg")


def stops_csv(rows: Sequence[StopError]) -> str:
    """CSV of the stop errors (signed errors, estimate - reference), one row per stop."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for r in rows:
        dx, dy, d, dyaw = r.errors
        writer.writerow([r.label, f"{r.start:.3f}", f"{r.end:.3f}", r.n,
                         f"{r.ref[0]:.5f}", f"{r.ref[1]:.5f}", f"{np.degrees(r.ref[2]):.4f}",
                         f"{r.est[0]:.5f}", f"{r.est[1]:.5f}", f"{np.degrees(r.est[2]):.4f}",
                         f"{100 * dx:.4f}", f"{100 * dy:.4f}", f"{100 * d:.4f}", f"{np.degrees(dyaw):.4f}"])
    return out.getvalue()


def pose_errors_csv(errors: PoseErrors) -> str:
    """CSV of the per-pose errors (evo's APE): stamp, position error (mm), its x, y, z, rotation (deg)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(("t", "position_mm", "dx_mm", "dy_mm", "dz_mm", "rotation_deg"))
    for t, d, xyz, r in zip(errors.stamps, errors.position_m, errors.xyz_m, errors.rotation_deg):
        writer.writerow([f"{t:.6f}", f"{1000 * d:.3f}", f"{1000 * xyz[0]:.3f}", f"{1000 * xyz[1]:.3f}",
                         f"{1000 * xyz[2]:.3f}", f"{r:.4f}"])
    return out.getvalue()


def write_tables(out_dir: str, position_rows: Sequence[StopError], orientation_rows: Sequence[StopError],
                 reference_name: str = "reference", frame: str = "the reference's frame",
                 titles: Tuple[str, str] = ("Table I. Errors in position", "Table II. Errors in orientation"),
                 prefix: str = "") -> Dict[str, str]:
    """Write ``table1.md``/``table1.csv`` and ``table2.md``/``table2.csv`` into ``out_dir``.

    Returns {name: path}. An empty row list skips its table.
    """
    paths: Dict[str, str] = {}
    for key, rows, table in (("table1", position_rows, position_table_markdown),
                             ("table2", orientation_rows, orientation_table_markdown)):
        if not rows:
            continue
        title = titles[0] if key == "table1" else titles[1]
        paths[f"{key}_md"] = os.path.join(out_dir, f"{prefix}{key}.md")
        atomic_write_text(paths[f"{key}_md"], table(rows, title=title, reference_name=reference_name, frame=frame),
                          keep_backup=False)
        paths[f"{key}_csv"] = os.path.join(out_dir, f"{prefix}{key}.csv")
        atomic_write_text(paths[f"{key}_csv"], stops_csv(rows), keep_backup=False)
    return paths
