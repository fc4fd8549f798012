"""``aruco_ring calibrate-ring``: the ring's extrinsics from a recording, starting from rough values.

The bag: the robot turning on the spot (a full turn or more) and driving among markers, each
camera's detections (or images) as ``build-map`` reads them (``ros/bag_source.py``; the rough ring
file gives the topics' namespaces and the intrinsics without camera_info; ``/tf_static`` is not
used: its extrinsics are what is being calibrated). Optional: an odometry topic
(``nav_msgs/Odometry``, default ``odom`` when the bag has it) gives base_link's heading; a known
map (``--map``, floor frame) gives the ring's height. :func:`ring_calibration.calibrate_ring` does
the work; the ring file is written atomically (the previous one kept as ``.bak``) in the ring
file's format with each camera's ``extrinsics_std``.
"""
from __future__ import annotations

import argparse
import sys
from typing import List

import numpy as np

from .. import geometry as geo
from ..errors import ConfigError
from ..marker_map import MarkerMap
from ..ring import CameraRing
from ..ring_calibration import CalibrationOptions, calibrate_ring

COMMAND = "calibrate-ring"
HELP = "calibrate the ring's extrinsics from a bag of the robot turning and driving among markers (rough values in)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag with each camera's fiducial_vertices (or AprilTag detections, or images) "
                                    "and camera_info, of the robot turning on the spot and driving among markers")
    parser.add_argument("--ring", required=True, help="the rough ring file (a drawing's values; config/ring.yaml's "
                                                      "format)")
    parser.add_argument("--out", required=True, help="calibrated ring file to write (atomically; old one kept as .bak)")
    parser.add_argument("--map", help="a known marker map (floor frame: also gives the ring's height)")
    parser.add_argument("--odom", help="odometry topic (nav_msgs/Odometry; default: odom when the bag has it; "
                                       "'none' to ignore it)")
    parser.add_argument("--config", help="the mapper's parameter file for markers/* and input/* (default: "
                                         "config/mapping.yaml)")
    parser.add_argument("--fiducial-len", type=float, help="markers/fiducial_len: marker side, m (the scale)")
    parser.add_argument("--fiducial-len-override", help='markers/fiducial_len_override: "1-10: 0.05, 12: 0.06"')
    parser.add_argument("--max-frames", type=int, default=CalibrationOptions.max_frames,
                        help="frames used, evenly spread over the bag (default %(default)s)")
    parser.add_argument("--wiggle", choices=("auto", "off"), default=CalibrationOptions.wiggle,
                        help="auto: when the ring file declares a camera's wiggle (its per-frame freedom on the ring, "
                             "e.g. imported from TagSLAM), calibrate the fixed pose it wiggles about; off: a rigid "
                             "ring whatever the file declares (default %(default)s)")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr even when it is not a terminal")


def _read_frames(args: argparse.Namespace, ring: CameraRing):
    from ..config import load_yaml_config, with_overrides
    from ..pipeline import MappingPipeline
    from ..ros.bag_source import BagSource, package_file
    from ..schemas import MapperConfig

    config = load_yaml_config(MapperConfig, args.config or package_file("config", "mapping.yaml"), {
        "markers.fiducial_len": args.fiducial_len, "markers.fiducial_len_override": args.fiducial_len_override})
    config = with_overrides(config, {"input.use_tf": False})

    class _Collect(MappingPipeline):
        """The mapper's way in (frame assembly, sanitising), keeping the ring frames."""

        def __init__(self, *a):
            super().__init__(*a)
            self.collected: List = []

        def _add(self, frames) -> int:
            self.collected += frames
            return len(frames)

    pipe = _Collect(config, ring)
    with BagSource(args.bag, ring, progress=args.progress or None) as source:
        source.run(pipe, command=COMMAND)
        topics = dict(source.topics)
    return pipe.collected, config.markers.sizes(), topics


def _read_odometry(args: argparse.Namespace, topics):
    from ..ros.bag_source import read_reference

    if args.odom == "none":
        return None
    topic = args.odom
    if topic is None:
        cands = [t for t, (typ, _) in topics.items() if typ == "nav_msgs/Odometry" and t.strip("/") == "odom"]
        if not cands:
            return None
        topic = cands[0]
    stamps, poses, what = read_reference(args.bag, topic=topic, progress=args.progress or None)
    sys.stdout.write(f"odometry: {len(stamps)} poses from {topic} ({what})\n")
    return list(zip([float(t) for t in stamps], list(poses)))


def _largest_difference(a: CameraRing, b: CameraRing) -> str:
    """The largest difference of a camera's pose relative to camera 0 between two rings (mm / deg)."""
    c0 = a.names[0]
    d = [geo.pose_distance(geo.inverse(a[c0].T_base_cam) @ a[c].T_base_cam,
                           geo.inverse(b[c0].T_base_cam) @ b[c].T_base_cam) for c in a.names[1:]] or [(0.0, 0.0)]
    return f"{1000 * max(t for t, _ in d):.1f} mm / {np.degrees(max(r for _, r in d)):.2f} deg (relative to {c0})"


def run(args: argparse.Namespace) -> int:
    try:
        from ..ros import bag_source  # noqa: F401  (needs rosbag)
    except ImportError as exc:
        sys.stderr.write(f"calibrate-ring: needs the ROS Python packages (rosbag; source .ws/env.sh): {exc}\n")
        return 2
    rough = CameraRing.load(args.ring)
    frames, sizes, topics = _read_frames(args, rough)
    if not frames:
        raise ConfigError("no usable ring frame in the bag (see the lines above)", path=args.bag)
    odometry = _read_odometry(args, topics)
    known = MarkerMap.load(args.map) if args.map else None
    cal = calibrate_ring(frames, rough, sizes, odometry=odometry, marker_map=known,
                         options=CalibrationOptions(max_frames=args.max_frames, wiggle=args.wiggle))
    cal.ring.save(args.out)
    out = sys.stdout
    out.write(f"ring: {args.out} ({cal.frames_used} frames, turned {cal.turn_deg:.0f} deg, drove {cal.travel_m:.1f} m; "
              f"bundle adjustment RMS {cal.rms_px_before:.2f} -> {cal.rms_px_after:.3f} px)\n")
    out.write(f"{'camera':>8} {'frames':>7} {'moved (mm)':>11} {'turned (deg)':>13} {'std (mm)':>9} {'std (deg)':>10}\n")
    for c in cal.ring:
        dt, dr = geo.pose_distance(rough[c.name].T_base_cam, c.T_base_cam)
        s = cal.std[c.name]
        out.write(f"{c.name:>8} {cal.camera_frames[c.name]:>7} {1000 * dt:>11.1f} {np.degrees(dr):>13.2f} "
                  f"{1000 * float(np.max(s[3:])):>9.2f} {float(np.degrees(np.max(s[:3]))):>10.3f}\n")
    if cal.wiggle is not None:
        w = cal.wiggle
        out.write(f"wiggle: {', '.join(w.wiggling)} declare {np.degrees(w.sigma[0]):.2g} deg / {1000 * w.sigma[1]:.2g} mm "
                  f"per frame: the extrinsics written are the fixed poses they wiggle about ({w.frames} frames, "
                  f"{len(w.rounds)} rounds, {w.cpu_s:.0f} s CPU; --wiggle off for a rigid ring); the rigid answer "
                  f"differs by up to {_largest_difference(cal.rigid_ring, cal.ring)}\n")
    for w in cal.warnings:
        out.write(f"warning: {w}\n")
    return 0
