"""``aruco_ring localize``: run the localization pipeline on a recorded bag, write a TUM trajectory.

Reads each ring camera's ``<namespace>/fiducial_vertices`` (fiducial_msgs/FiducialArray) from the
bag (and ``<namespace>/camera_info`` when recorded; the ring file's intrinsics otherwise), plus
``cmd_vel`` / ``odom`` for the gate, assembles ring frames by stamp exactly as the node does
(extrinsics from the ring file), runs :class:`tracker.RingTracker` and writes the filtered pose
per ring frame as ``t x y z qx qy qz qw`` (evo reads it). ``--csv`` adds per-frame diagnostics.
rosbag (Debian's python3-rosbag) is imported only inside this command.
"""
from __future__ import annotations

import argparse
import csv
import sys
from typing import Dict, List

import numpy as np

from ..errors import ArucoRingError, ConfigError
from ..evaluation.trajectories import trajectory, write_tum
from ..localization import LocalizationParams
from ..marker_map import MarkerMap
from ..ring import CameraRing
from ..detections import RingInputCore
from ..tracker import RingTracker

COMMAND = "localize"
HELP = "run the localizer on a bag of detections and write a TUM trajectory"

CSV_FIELDS = ["stamp", "x", "y", "yaw", "std_x", "std_y", "std_yaw", "meas_x", "meas_y", "meas_yaw", "method",
              "cameras", "markers", "residual_px", "gate", "time_jump"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag with <ns>/fiducial_vertices per camera")
    parser.add_argument("--ring", required=True, help="ring YAML file (config/ring.yaml)")
    parser.add_argument("--map", dest="map_file", required=True, help="marker map YAML")
    parser.add_argument("--out", required=True, help="output TUM trajectory")
    parser.add_argument("--fusion", choices=["paper", "joint"], default="joint")
    parser.add_argument("--csv", help="per-frame diagnostics CSV")
    parser.add_argument("--slop", type=float, default=0.03, help="ring frame grouping slop, s")


def run(args: argparse.Namespace) -> int:
    try:
        import rosbag  # noqa: F401  (Debian python3-rosbag)
    except ImportError:
        sys.stderr.write("localize: needs the rosbag Python module (apt install python3-rosbag, "
                         "then source .ws/env.sh)\n")
        return 2
    try:
        ring = CameraRing.load(args.ring)
        marker_map = MarkerMap.load(args.map_file)
    except ConfigError as exc:
        sys.stderr.write(f"localize: {exc}\n")
        return 1
    tracker = RingTracker(ring, marker_map, LocalizationParams(fusion=args.fusion))
    core = RingInputCore(ring, slop=args.slop, timeout=0.25, camera_info_fallback=True, extrinsics_from_ring=True)
    topics: Dict[str, tuple] = {}
    for cam in ring.cameras:
        ns = cam.namespace.strip("/")
        prefix = f"{ns}/" if ns else ""
        for variant in (prefix, "/" + prefix):
            topics[f"{variant}fiducial_vertices"] = ("fv", cam.name)
            topics[f"{variant}camera_info"] = ("ci", cam.name)
    for t in ("cmd_vel", "/cmd_vel", "odom", "/odom"):
        topics[t] = ("motion", t.strip("/"))
    stamps: List[float] = []
    poses: List[np.ndarray] = []
    rows: List[dict] = []

    def handle(frames) -> None:
        for frame in frames:
            try:
                out = tracker.process(frame)
            except ArucoRingError as exc:
                sys.stderr.write(f"localize: frame {frame.stamp:.3f}: {exc}\n")
                continue
            if out.pose is None:
                continue
            stamps.append(out.stamp)
            poses.append(out.pose)
            loc = out.localization
            meas = loc.se2 if loc.ok else (np.nan, np.nan, np.nan)
            std = np.sqrt(np.diag(out.covariance))
            rows.append({"stamp": f"{out.stamp:.6f}", "x": out.pose[0], "y": out.pose[1], "yaw": out.pose[2],
                         "std_x": std[0], "std_y": std[1], "std_yaw": std[2], "meas_x": meas[0], "meas_y": meas[1],
                         "meas_yaw": meas[2], "method": loc.method, "cameras": len(loc.used_cameras),
                         "markers": len(loc.marker_ids), "residual_px": loc.residual_rms,
                         "gate": out.decision.reason if out.decision else "", "time_jump": int(out.time_jump)})

    from ..ros.conversions import camera_info_to_model, fiducial_array_to_observations, stamp_to_sec

    import rosbag
    n_msgs = 0
    try:
        bag = rosbag.Bag(args.bag)
    except (OSError, rosbag.ROSBagException) as exc:
        sys.stderr.write(f"localize: cannot open {args.bag}: {exc}\n")
        return 1
    with bag:
        wanted = [t for t in bag.get_type_and_topic_info().topics if t in topics]
        if not any(topics[t][0] == "fv" for t in wanted):
            sys.stderr.write(f"localize: {args.bag} has no <ns>/fiducial_vertices topic of the ring's cameras\n")
            return 1
        for topic, msg, t in bag.read_messages(topics=wanted):
            kind, name = topics[topic]
            now = t.to_sec()
            try:
                if kind == "fv":
                    n_msgs += 1
                    frames, _, _ = core.add_detections(name, stamp_to_sec(msg.header.stamp),
                                                       fiducial_array_to_observations(msg), now)
                    handle(frames)
                elif kind == "ci":
                    core.set_camera_model(name, camera_info_to_model(msg, name=name))
                elif name == "cmd_vel":
                    tracker.set_motion("cmd_vel", float(np.hypot(msg.linear.x, msg.linear.y)), msg.angular.z, now)
                else:
                    tw = msg.twist.twist
                    tracker.set_motion("odom", float(np.hypot(tw.linear.x, tw.linear.y)), tw.angular.z,
                                       stamp_to_sec(msg.header.stamp))
            except ArucoRingError as exc:
                sys.stderr.write(f"localize: {topic} at {now:.3f}: {exc}\n")
            handle(core.poll(now))
        handle(core.poll(float("inf")))
    write_tum(args.out, trajectory(stamps, poses))
    if args.csv:
        with open(args.csv, "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
            w.writeheader()
            w.writerows(rows)
    sys.stdout.write(f"localize: {n_msgs} detection messages -> {len(stamps)} poses written to {args.out}"
                     f" ({tracker.time_jumps} time jumps, {tracker.gate.reinitializations} re-initialisations, "
                     f"rejected {tracker.rejected_counts})\n")
    return 0
