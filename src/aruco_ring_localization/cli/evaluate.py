"""``aruco_ring evaluate``: errors of an estimated trajectory against a reference (TUM files).

Time matching (nearest within ``--max-dt`` or interpolation), optional SE(2) least-squares
alignment of the estimate onto the reference (``--align se2``, the closed-form 2D Umeyama
without scale; ``none`` compares in the files' own frames), errors in x, y, Euclidean and
yaw; with ``--stops``, the stops of the reference (still for ``--stop-time`` s) become the rows
of the paper's Table I (position) and Table II (orientation). ``--out DIR`` writes the tables
(markdown + CSV), the matched pairs (CSV), the aligned estimate (TUM) and figures (PNG).
See docs/evaluation.md for the same numbers with ``evo``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from .. import trajectory as tr
from ..errors import ConfigError

COMMAND = "evaluate"
HELP = "errors of an estimated trajectory against a reference (TUM files): tables and figures"
DESCRIPTION = __doc__.split("\n\n")[1] if __doc__ else HELP


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", required=True, help="reference trajectory, TUM (t x y z qx qy qz qw)")
    parser.add_argument("--estimate", required=True, help="estimated trajectory, TUM")
    parser.add_argument("--align", choices=("se2", "none"), default="se2",
                        help="fit the estimate's frame to the reference's (se2, default) or not (none)")
    parser.add_argument("--n-to-align", type=int, default=-1,
                        help="use only the first N matched poses for the alignment (-1: all)")
    parser.add_argument("--match", choices=("nearest", "interpolate"), default="nearest",
                        help="time matching: nearest reference pose, or interpolated reference")
    parser.add_argument("--max-dt", type=float, default=0.05, help="largest time difference accepted (s)")
    parser.add_argument("--stops", action="store_true",
                        help="report per-stop errors (Table I / Table II) where the reference stood still")
    parser.add_argument("--stop-time", type=float, default=2.0, help="minimum stop duration (s)")
    parser.add_argument("--stop-tolerance", type=float, default=0.01,
                        help="largest reference motion within a stop (m; yaw tolerance is 0.5 deg)")
    parser.add_argument("--settle", type=float, default=0.0, help="seconds ignored at the start of each stop")
    parser.add_argument("--out", help="directory for tables (md, csv), figures (png) and summary.json")


def run(args: argparse.Namespace) -> int:
    ref = tr.read_tum(args.reference)
    est = tr.read_tum(args.estimate)
    pairs = tr.match(ref, est, max_dt=args.max_dt, method=args.match)
    if len(pairs) < 1:
        raise ConfigError(f"no estimate pose within {args.max_dt} s of a reference pose "
                          f"(reference {ref.stamps[0]:.3f}..{ref.stamps[-1]:.3f} s, "
                          f"estimate {est.stamps[0]:.3f}..{est.stamps[-1]:.3f} s)")
    out = sys.stdout
    out.write(f"matched {len(pairs)} of {len(est)} estimate poses ({args.match}, max_dt {args.max_dt} s)\n")
    T = np.zeros(3)
    if args.align == "se2":
        n = len(pairs) if args.n_to_align < 0 else max(1, min(args.n_to_align, len(pairs)))
        T = tr.align_se2(pairs.est[:n], pairs.ref[:n])
        pairs = pairs.with_estimate(tr.apply_se2(T, pairs.est))
        out.write(f"SE(2) alignment over {n} pairs: x {T[0]:+.4f} m, y {T[1]:+.4f} m, "
                  f"yaw {np.degrees(T[2]):+.4f} deg\n")
    stats = tr.error_statistics(tr.pose_errors(pairs.ref, pairs.est))
    out.write(f"all matched poses: position error median {stats['position_cm_median']:.3f} cm, "
              f"RMS {stats['position_cm_rms']:.3f} cm, max {stats['position_cm_max']:.3f} cm; "
              f"|yaw| mean {stats['yaw_deg_mean_abs']:.3f} deg, max {stats['yaw_deg_max_abs']:.3f} deg\n")
    summary = {"matched": len(pairs), "alignment": {"method": args.align, "x_m": float(T[0]), "y_m": float(T[1]),
                                                    "yaw_deg": float(np.degrees(T[2]))},
               "all": stats}
    rows = []
    if args.stops:
        stops = tr.detect_stops(pairs.stamps, pairs.ref, min_duration=args.stop_time, pos_tol=args.stop_tolerance,
                                settle=args.settle)
        rows = tr.stop_errors(pairs, stops)
        out.write(f"\n{len(rows)} stops of at least {args.stop_time} s\n\n")
        if rows:
            out.write(tr.position_table_markdown(rows) + "\n" + tr.orientation_table_markdown(rows))
            summary["stops"] = tr.summarize(rows)
    if args.out:
        _write_outputs(args.out, pairs, rows, est, T, summary)
        out.write(f"\nwrote {args.out}/\n")
    return 0


def _write_outputs(out_dir: str, pairs: tr.MatchedPairs, rows, est: tr.Trajectory, T: np.ndarray, summary) -> None:
    from .. import plots
    from ..fileio import atomic_write_text

    os.makedirs(out_dir, exist_ok=True)
    atomic_write_text(os.path.join(out_dir, "pairs.csv"), tr.pairs_csv(pairs), keep_backup=False)
    aligned = tr.Trajectory.from_se2(est.sorted().stamps, tr.apply_se2(T, est.sorted().se2))
    tr.write_tum(os.path.join(out_dir, "estimate_aligned.tum"), aligned, header="estimate after SE(2) alignment")
    if rows:
        tr.write_tables(out_dir, rows, rows)
        plots.plot_positions(os.path.join(out_dir, "positions.png"), np.array([r.ref[:2] for r in rows]),
                             np.array([r.est[:2] for r in rows]), labels=[r.label for r in rows],
                             errors_cm=[100 * r.errors[2] for r in rows], title="Stops: reference and estimate")
        plots.plot_orientations(os.path.join(out_dir, "orientations.png"), [r.ref[2] for r in rows],
                                [r.est[2] for r in rows], labels=[r.label for r in rows],
                                title="Stops: reference (blue) and estimated (red) headings")
    plots.plot_trajectory(os.path.join(out_dir, "trajectory.png"), pairs.stamps, pairs.ref, pairs.est)
    atomic_write_text(os.path.join(out_dir, "summary.json"), json.dumps(summary, indent=2) + "\n", keep_backup=False)
