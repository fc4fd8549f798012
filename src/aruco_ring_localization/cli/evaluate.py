"""``aruco_ring evaluate EST REF``: errors of an estimated trajectory against a reference (TUM files).

Both files are 6-DOF TUM (``t x y z qx qy qz qw``). Poses are paired by stamp (the nearest within
``--max-dt`` s, evo's association); ``--align`` chooses how the estimate's frame is put onto the
reference's: ``none`` (default: the strict convention, the files are compared in their own
frames), ``se2`` (a fitted rotation about z and x, y translation) or ``se3`` (a fitted rigid
motion, evo's Umeyama). A fitted alignment absorbs any constant error of the estimate's frame, so
its numbers are a diagnostic and the output says so. Reported: evo's absolute pose error,
position (median, p95, max, in mm) and rotation angle (deg); with ``--stops``, the stops of the
reference (still for ``--stop-time`` s) become the rows of the paper's Table I (position) and
Table II (orientation). ``--out DIR`` writes summary.json, the per-pose errors (CSV), the aligned
estimate (6-DOF TUM) and the tables; ``--plot`` adds figures (PNG) there.
See docs/evaluation.md for the same numbers with ``evo_ape``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from ..errors import ConfigError
from ..evaluation import trajectories as tj
from ..evaluation.stops import detect_stops, stop_errors, summarize
from ..evaluation.tables import orientation_table_markdown, pose_errors_csv, position_table_markdown, write_tables
from ..fileio import atomic_write_text

COMMAND = "evaluate"
HELP = "errors of an estimated trajectory against a reference (TUM files): APE, tables, figures"
DESCRIPTION = __doc__.split("\n\n")[1] if __doc__ else HELP


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("estimate", nargs="?", help="estimated trajectory, TUM (t x y z qx qy qz qw)")
    parser.add_argument("reference", nargs="?", help="reference trajectory, TUM")
    parser.add_argument("--estimate", dest="estimate_option", metavar="EST", help="the same as the first argument")
    parser.add_argument("--reference", dest="reference_option", metavar="REF", help="the same as the second argument")
    parser.add_argument("--align", choices=tj.ALIGNMENTS, default="none",
                        help="none (default, strict: the files' own frames), or a fitted se2 / se3 alignment of "
                             "the estimate onto the reference (a diagnostic)")
    parser.add_argument("--n-to-align", type=int, default=-1,
                        help="fit the alignment on the first N pairs only (-1: all)")
    parser.add_argument("--max-dt", type=float, default=0.05, help="largest stamp difference of a pair (s)")
    parser.add_argument("--t-offset", type=float, default=0.0, help="seconds added to the estimate's stamps")
    parser.add_argument("--stops", action="store_true",
                        help="report per-stop errors (Table I / Table II) where the reference stood still")
    parser.add_argument("--stop-time", type=float, default=2.0, help="minimum stop duration (s)")
    parser.add_argument("--stop-tolerance", type=float, default=0.01,
                        help="largest reference motion within a stop (m; yaw tolerance is 0.5 deg)")
    parser.add_argument("--settle", type=float, default=0.0, help="seconds ignored at the start of each stop")
    parser.add_argument("--out", help="directory for summary.json, errors.csv, estimate_aligned.tum and tables")
    parser.add_argument("--plot", action="store_true", help="also write figures (PNG) into --out")


def _files(args: argparse.Namespace):
    """(estimate, reference): the options win; the positionals fill what they leave, in that order."""
    positional = [p for p in (args.estimate, args.reference) if p]
    est = args.estimate_option or (positional.pop(0) if positional else None)
    ref = args.reference_option or (positional.pop(0) if positional else None)
    if not est or not ref or positional:
        raise ConfigError("give one estimate and one reference: aruco_ring evaluate EST.tum REF.tum")
    return est, ref


def run(args: argparse.Namespace) -> int:
    est_path, ref_path = _files(args)
    if args.plot and not args.out:
        raise ConfigError("--plot writes its figures into --out DIR: give one")
    ref_all, est_all = tj.read_tum(ref_path), tj.read_tum(est_path)
    ref, est = tj.associate(ref_all, est_all, max_dt=args.max_dt, offset=args.t_offset)
    out = sys.stdout
    out.write(f"{ref.num_poses} pairs: {est_all.num_poses} estimate and {ref_all.num_poses} reference poses, "
              f"nearest stamp within {args.max_dt} s\n")
    alignment = tj.fit_alignment(ref, est, args.align, n=args.n_to_align)
    out.write(alignment.describe() + "\n")
    aligned = alignment.apply(est)
    errors = tj.ape(ref, aligned)
    stats = errors.statistics()
    out.write(("DIAGNOSTIC (after the fitted alignment) " if alignment.fitted else "") + tj.format_statistics(stats) + "\n")
    summary = {"estimate": est_path, "reference": ref_path, "pairs": ref.num_poses, "max_dt_s": args.max_dt,
               "alignment": alignment.as_dict(), "ape": stats}
    rows = []
    pairs = tj.MatchedPairs.of(ref, aligned)
    if args.stops:
        stops = detect_stops(pairs.stamps, pairs.ref, min_duration=args.stop_time, pos_tol=args.stop_tolerance,
                             settle=args.settle)
        rows = stop_errors(pairs, stops)
        out.write(f"\n{len(rows)} stops of at least {args.stop_time} s\n\n")
        if rows:
            frame = _frame(alignment)
            out.write(position_table_markdown(rows, frame=frame) + "\n" + orientation_table_markdown(rows, frame=frame))
            summary["stops"] = summarize(rows)
    if args.out:
        _write_outputs(args.out, errors, rows, aligned, alignment, summary, args.plot, pairs)
        out.write(f"\nwrote {args.out}/\n")
    return 0


def _frame(alignment: tj.Alignment) -> str:
    return "reference's frame" + (f" (after the fitted {alignment.method} alignment)" if alignment.fitted else "")


def _write_outputs(out_dir: str, errors: tj.PoseErrors, rows, aligned, alignment: tj.Alignment, summary,
                   plot: bool, pairs: tj.MatchedPairs) -> None:
    os.makedirs(out_dir, exist_ok=True)
    atomic_write_text(os.path.join(out_dir, "errors.csv"), pose_errors_csv(errors), keep_backup=False)
    tj.write_tum(os.path.join(out_dir, "estimate_aligned.tum"), aligned,
                 header=f"estimate after alignment {alignment.method} (paired poses only)")
    if rows:
        write_tables(out_dir, rows, rows, frame=_frame(alignment))
    atomic_write_text(os.path.join(out_dir, "summary.json"), json.dumps(summary, indent=2) + "\n", keep_backup=False)
    if not plot:
        return
    from ..evaluation import figures

    figures.plot_trajectory(os.path.join(out_dir, "trajectory.png"), pairs.stamps, pairs.ref, pairs.est,
                            title=f"Trajectory (alignment {alignment.method})")
    if rows:
        figures.plot_positions(os.path.join(out_dir, "positions.png"), np.array([r.ref[:2] for r in rows]),
                               np.array([r.est[:2] for r in rows]), labels=[r.label for r in rows],
                               errors_cm=[100 * r.errors[2] for r in rows], title="Stops: reference and estimate")
        figures.plot_orientations(os.path.join(out_dir, "orientations.png"), [r.ref[2] for r in rows],
                                  [r.est[2] for r in rows], labels=[r.label for r in rows],
                                  title="Stops: reference (blue) and estimated (red) headings")
