"""``aruco_ring localize``: the localizer node's pipeline on a recorded bag, to a TUM trajectory.

The pipeline is :class:`pipeline.LocalizationPipeline` built from the node's own parameters
(``config/localization.yaml``, or ``--config FILE``; the options below override single keys), so
the poses are the ones the node would have published (a rostest checks it to 1e-9). The bag is
read by ``ros/bag_source.py`` (each camera's ``fiducial_vertices``, or images through the
detector; ``camera_info``; ``cmd_vel`` / ``odom``; extrinsics from ``/tf_static``, else the ring
file's). Output: one TUM line ``t x y z qx qy qz qw`` (evo reads it) per pose:

* ``--output filtered`` (default): the filtered pose, as ``~pose`` (x, y, yaw at the measured
  height); with ``--6dof`` the full pose of the 6-DOF tracker (``filter/model: 6dof``, module
  ``tracker6``: a handheld or flying rig), unless ``--filter-model planar`` keeps the planar filter
  (then roll and pitch are the last accepted measurement's);
* ``--output measurement``: the estimator's per-frame pose (planar; ``--6dof``: the full pose).

``--csv`` adds per-frame diagnostics (full precision).
"""
from __future__ import annotations

import argparse
import csv
import sys
from typing import List

import numpy as np

from .. import geometry as geo
from ..config import load_yaml_config
from ..errors import ConfigError
from ..evaluation.trajectories import trajectory, write_tum
from ..fileio import atomic_write_text
from ..marker_map import MarkerMap
from ..pipeline import LocalizationPipeline, PoseOutput
from ..ring import CameraRing
from ..schemas import LocalizerConfig

COMMAND = "localize"
HELP = ("run the localizer's pipeline on a bag of detections (fiducial_vertices, AprilTag, or images) and write a "
        "TUM trajectory")

CSV_FIELDS = ["stamp", "x", "y", "yaw", "std_x", "std_y", "std_yaw", "meas_x", "meas_y", "meas_yaw", "method",
              "cameras", "markers", "residual_px", "gate", "time_jump", "z", "predicted_only"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag with <ns>/fiducial_vertices (or AprilTag detections, or images) per camera")
    parser.add_argument("--map", dest="map_file", required=True, help="marker map YAML")
    parser.add_argument("--out", required=True, help="output TUM trajectory")
    parser.add_argument("--ring", help="ring YAML file (default: the config's ring_file, else config/ring.yaml)")
    parser.add_argument("--config", help="the localizer's parameter file (default: config/localization.yaml)")
    parser.add_argument("--fusion", choices=["paper", "joint"], help="estimator/fusion (default: the config's)")
    parser.add_argument("--slop", help="input/slop: auto or a ring frame grouping slop, s (default: the config's)")
    parser.add_argument("--ignore-fiducials", help='input/ignore_fiducials: ids never used, "1,4,9-12"')
    parser.add_argument("--output", choices=["filtered", "measurement"], default="filtered",
                        help="filtered poses (as ~pose) or the estimator's per-frame poses")
    parser.add_argument("--6dof", dest="six_dof", action="store_true",
                        help="full poses (z, roll, pitch from the estimator) instead of planar ones")
    parser.add_argument("--filter-model", choices=["planar", "6dof"],
                        help="filter/model (default: 6dof with --6dof, else the config's)")
    parser.add_argument("--csv", help="per-frame diagnostics CSV")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr even when it is not a terminal")


def load_config(args: argparse.Namespace) -> LocalizerConfig:
    """The node's parameters from ``--config`` (or the package's file) with the options applied."""
    from ..ros.bag_source import package_file

    path = args.config or package_file("config", "localization.yaml")
    return load_yaml_config(LocalizerConfig, path, {
        "map_file": args.map_file, "estimator.fusion": args.fusion, "input.slop": args.slop,
        "input.ignore_fiducials": args.ignore_fiducials,
        "filter.model": getattr(args, "filter_model", None) or ("6dof" if getattr(args, "six_dof", False) else None)})


def run(args: argparse.Namespace) -> int:
    try:
        from ..ros.bag_source import BagSource, package_file
    except ImportError as exc:
        sys.stderr.write(f"localize: needs the ROS Python packages (rosbag; source .ws/env.sh): {exc}\n")
        return 2
    try:
        config = load_config(args)
        ring = CameraRing.load(args.ring or config.ring_file or package_file("config", "ring.yaml"))
        marker_map = MarkerMap.load(args.map_file)
        pipeline = LocalizationPipeline(config, ring, marker_map)
        with BagSource(args.bag, ring, progress=args.progress or None) as source:
            outputs: List[PoseOutput] = source.run(pipeline, command="localize")
    except ConfigError as exc:
        sys.stderr.write(f"localize: {exc}\n")
        return 1
    stamps, poses = [], []
    for out in outputs:
        if args.output == "filtered":
            stamps.append(out.stamp)
            poses.append(out.T_map_base_6dof if args.six_dof else out.T_map_base)
        elif out.track.localization.ok and not out.predicted_only:
            T = out.track.localization.T_map_base
            stamps.append(out.stamp)
            poses.append(T if args.six_dof else geo.transform_from_se2(*geo.se2_from_transform(T), z=T[2, 3]))
    if not stamps:
        sys.stderr.write(f"localize: no pose from {args.bag} (no mapped marker seen?); {args.out} not written\n")
        return 1
    write_tum(args.out, trajectory(stamps, poses))
    if args.csv:
        _write_csv(args.csv, outputs)
    sys.stdout.write(f"localize: {pipeline.input.frames_in} detection messages -> {pipeline.frames} ring frames -> "
                     f"{len(stamps)} poses ({args.output}{', 6 dof' if args.six_dof else ''}) written to {args.out} "
                     f"({pipeline.dropped_stale} stale frames dropped, {pipeline.time_jumps} time jumps, "
                     f"{pipeline.gate.reinitializations} re-initialisations, rejected {pipeline.rejected_counts})\n")
    return 0


def _write_csv(path: str, outputs: List[PoseOutput]) -> None:
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for out in outputs:
        loc = out.track.localization
        x, y, yaw = out.track.pose
        meas = loc.se2 if loc.ok else (np.nan, np.nan, np.nan)
        std = np.sqrt(np.diag(out.track.covariance))
        # repr-exact floats: the rostest compares these with the node's poses to 1e-9.
        w.writerow({"stamp": repr(float(out.stamp)), "x": repr(float(x)), "y": repr(float(y)),
                    "yaw": repr(float(yaw)), "std_x": std[0], "std_y": std[1], "std_yaw": std[2],
                    "meas_x": meas[0], "meas_y": meas[1], "meas_yaw": meas[2], "method": loc.method,
                    "cameras": len(loc.used_cameras), "markers": len(loc.marker_ids),
                    "residual_px": loc.residual_rms, "gate": out.track.decision.reason if out.track.decision else "",
                    "time_jump": int(out.track.time_jump), "z": repr(float(out.T_map_base[2, 3])),
                    "predicted_only": int(out.predicted_only)})
    atomic_write_text(path, buf.getvalue())
