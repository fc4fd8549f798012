"""``aruco_ring build-map``: build a marker map offline from a recorded bag.

Reads every camera's ``<ns>/fiducial_vertices`` (fiducial_msgs/FiducialArray) and
``<ns>/camera_info`` from the bag, the extrinsics from ``/tf_static`` when the bag has them for
``base_link -> <camera frame>`` (else the ring file's), groups the detections into ring frames by
stamp, runs :class:`mapping.MapBuilder` and writes the map atomically. Progress goes to stderr,
a summary table to stdout.
"""
from __future__ import annotations

import argparse
import sys
from typing import Dict

import numpy as np

from .. import geometry as geo
from ..errors import ArucoRingError, ConfigError
from ..detections import RingFrameAssembler
from ..mapping import MapBuilder
from ..markers import MarkerSizes, parse_id_list
from ..ring import CameraRing
from ..detections import RingInputCore

COMMAND = "build-map"
HELP = "build a marker map from a bag of fiducial_vertices + camera_info (+ /tf_static)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag with <ns>/fiducial_vertices and <ns>/camera_info of the ring's cameras")
    parser.add_argument("--ring", required=True, help="ring YAML file (config/ring.yaml)")
    parser.add_argument("--out", required=True, help="map YAML to write (atomically; old one kept as .bak)")
    parser.add_argument("--method", choices=("paper", "refined"), default="refined")
    parser.add_argument("--reference-marker", type=int, default=None, help="id fixing the map frame")
    parser.add_argument("--fiducial-len", type=float, default=0.2, help="marker side, m")
    parser.add_argument("--fiducial-len-override", default="", help='per-id sizes "1-10: 0.05, 12: 0.06"')
    parser.add_argument("--ignore-fiducials", default="", help='ids to ignore "1,4,9-12"')
    parser.add_argument("--slop", type=float, default=0.03, help="stamp grouping tolerance, s")
    parser.add_argument("--map-frame", default="map")


def _progress(done: int, total: int, width: int = 40) -> None:
    frac = done / total if total else 1.0
    bar = "#" * int(frac * width)
    sys.stderr.write(f"\r[{bar:<{width}}] {100 * frac:5.1f}% ({done}/{total} messages)")
    sys.stderr.flush()


def _bag_extrinsics(bag, ring: CameraRing) -> Dict[str, np.ndarray]:
    """T_base_cam per camera from /tf_static when the bag has a direct base -> camera transform."""
    out: Dict[str, np.ndarray] = {}
    for _, msg, _ in bag.read_messages(topics=["/tf_static"]):
        for ts in msg.transforms:
            cam = ring.by_frame(ts.child_frame_id)
            if cam is not None and ts.header.frame_id.lstrip("/") == ring.base_frame:
                t, q = ts.transform.translation, ts.transform.rotation
                out[cam.name] = geo.transform_from_translation_quaternion([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
    return out


def run(args: argparse.Namespace) -> int:
    try:
        import rosbag
    except ImportError:
        sys.stderr.write("build-map needs the ROS python packages (source .ws/env.sh)\n")
        return 2
    from ..ros.conversions import camera_info_to_model, fiducial_array_to_observations, stamp_to_sec

    ring = CameraRing.load(args.ring)
    sizes = MarkerSizes.parse(args.fiducial_len, args.fiducial_len_override)
    ignore = parse_id_list(args.ignore_fiducials, key="--ignore-fiducials")
    try:
        bag = rosbag.Bag(args.bag)
    except (OSError, rosbag.ROSBagException) as exc:
        raise ConfigError(f"cannot open bag ({exc})", path=args.bag) from None
    with bag:
        extr = _bag_extrinsics(bag, ring)
        core = RingInputCore(ring, slop=args.slop, timeout=1e9, ignore_ids=ignore, camera_info_fallback=True,
                             extrinsics_from_ring=True)
        for name, T in extr.items():
            core.set_extrinsics(name, T)
        sys.stderr.write(f"extrinsics: {len(extr)} cameras from /tf_static, {len(ring) - len(extr)} from {args.ring}\n")
        topics = {}
        for cam in ring.cameras:
            ns = cam.namespace.strip("/")
            topics[f"/{ns}/fiducial_vertices"] = ("fid", cam.name)
            topics[f"/{ns}/camera_info"] = ("info", cam.name)
        total = sum(bag.get_message_count(topic_filters=[t]) for t in topics)
        if not total:
            raise ConfigError(f"no message on any of {sorted(topics)}", path=args.bag)
        builder = MapBuilder(core.ring, sizes, method=args.method, reference_marker=args.reference_marker,
                             frame_id=args.map_frame, ignore_ids=ignore)
        # Bags are replayed in stamp order: a group is complete when every camera reported, or when
        # a later stamp arrives (the assembler's "now" is the bag time here, timeout = 1 slop).
        core.assembler = RingFrameAssembler(core.camera_names, slop=args.slop, timeout=max(4 * args.slop, 0.1))
        done = 0
        for topic, msg, t in bag.read_messages(topics=list(topics)):
            kind, name = topics[topic]
            now = t.to_sec()
            if kind == "info":
                try:
                    core.set_camera_model(name, camera_info_to_model(msg, name))
                except ArucoRingError as exc:
                    sys.stderr.write(f"\n{topic}: {exc}\n")
            else:
                obs = fiducial_array_to_observations(msg)
                frames, _, _ = core.add_detections(name, stamp_to_sec(msg.header.stamp), obs, now)
                for f in frames:
                    builder.add_frame(f)
            done += 1
            if done % 200 == 0 or done == total:
                _progress(done, total)
        for f in core.poll(float("inf")):
            builder.add_frame(f)
        sys.stderr.write("\n")
    builder.ring = core.ring
    m = builder.build()
    m.save(args.out)
    _print_summary(builder, m, args.out)
    return 0


def _print_summary(builder: MapBuilder, m, path: str) -> None:
    s = builder.summary()
    out = sys.stdout
    out.write(f"map: {path} ({m.method}, frame '{m.frame_id}', reference marker {m.reference_marker})\n")
    out.write(f"frames {s['frames']}, stations {s['linked_stations']}/{s['stations']}\n")
    out.write(f"{'id':>6} {'x (m)':>9} {'y (m)':>9} {'z (m)':>9} {'std (mm)':>9} {'obs':>6}\n")
    for e in m:
        t = e.T_map_marker[:3, 3]
        out.write(f"{e.marker_id:>6} {t[0]:>9.3f} {t[1]:>9.3f} {t[2]:>9.3f} "
                  f"{1000 * float(np.max(e.position_std)):>9.2f} {e.observations:>6}\n")
    if s["unlinked"]:
        out.write(f"seen but never linked to the map (no common view): {s['unlinked']}\n")
    for mid, why in s["rejected"].items():
        out.write(f"marker {mid} not mapped: {why}\n")
    if builder.last_ba is not None and m.method == "refined":
        ba = builder.last_ba
        out.write(f"bundle adjustment: RMS {ba.rms_px_before:.3f} -> {ba.rms_px_after:.3f} px, {ba.seconds:.2f} s\n")
