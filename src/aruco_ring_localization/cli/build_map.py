"""``aruco_ring build-map``: the mapper node's pipeline on a recorded bag, to a map file.

The pipeline is :class:`pipeline.MappingPipeline` built from the mapper's own parameters
(``config/mapping.yaml``, or ``--config FILE``; the options below override single keys), so the
map is the one the mapper node saves from the same messages (a rostest checks it to 1e-9). The bag
is read by ``ros/bag_source.py`` (each camera's ``fiducial_vertices``, or images through the
detector; ``camera_info``; extrinsics from ``/tf_static``, else the ring file's). The map is
written through :meth:`MapBuilder.save_map` (atomically, sanity-checked, previous file kept as
``.bak``).

``--update MAP --markers ID ...`` re-maps those markers (moved ones) from the bag with every other
marker of MAP fixed: the localizer's pipeline (``config/localization.yaml``, or ``--config``: then
the localizer's file) runs on the bag with those markers kept out of the pose, their observations
are collected with the robot poses from the others, and each is re-estimated in 6 DOF
(:func:`marker_check.estimate_marker_pose`). MAP (or ``--out``) is written atomically, keeping
``marker_check.backups`` generations (``.bak``, ``.bak.2``, ...), as the map savers do.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

import numpy as np

from ..anchors import measurement_lines
from ..config import load_yaml_config
from ..errors import ConfigError
from ..pipeline import MappingPipeline
from ..ring import CameraRing
from ..schemas import MapperConfig

COMMAND = "build-map"
HELP = ("build a marker map from a bag of fiducial_vertices (or AprilTag detections, or images) + camera_info "
        "(+ /tf_static)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="rosbag with <ns>/fiducial_vertices (or AprilTag detections, or images) and "
                                    "<ns>/camera_info")
    parser.add_argument("--out", help="map YAML to write (atomically; old one kept as .bak); required unless "
                                      "--update (default there: the updated map itself)")
    parser.add_argument("--update", metavar="MAP", help="re-map --markers in MAP from the bag, the other markers "
                                                        "fixed (moved markers); --config is then the localizer's")
    parser.add_argument("--markers", nargs="+", metavar="ID", help="with --update: the marker ids to re-map")
    parser.add_argument("--ring", help="ring YAML file (default: the config's ring_file, else config/ring.yaml)")
    parser.add_argument("--config", help="the mapper's parameter file (default: config/mapping.yaml); with --update "
                        "the localizer's (default: config/localization.yaml)")
    parser.add_argument("--method", choices=("paper", "refined"), help="map/method (default: the config's)")
    parser.add_argument("--reference-marker", type=int, help="map/reference_marker: id fixing the map frame")
    parser.add_argument("--anchors", metavar="FILE",
                        help="map/anchors_file: surveyed markers (YAML, docs/formats.md) that define the map frame")
    parser.add_argument("--boards", metavar="TAGSLAM_YAML",
                        help="map/boards_file: rigid boards of markers with known layouts (a tagslam.yaml's board / "
                             "staggered_board bodies): each board's markers are mapped together")
    parser.add_argument("--fiducial-len", type=float, help="markers/fiducial_len: marker side, m")
    parser.add_argument("--fiducial-len-override", help='markers/fiducial_len_override: "1-10: 0.05, 12: 0.06"')
    parser.add_argument("--ignore-fiducials", help='input/ignore_fiducials: ids to ignore "1,4,9-12"')
    parser.add_argument("--slop", help="input/slop: auto (the default: one frame period of the cameras' stamps) or a stamp grouping tolerance, s")
    parser.add_argument("--map-frame", help="map/map_frame")
    parser.add_argument("--frame", choices=("floor", "marker"),
                        help="mapping/frame: floor = on the floor below the reference marker, z up (ground "
                             "robots); marker = the reference marker's own frame (fiducial_slam's; handheld rigs)")
    parser.add_argument("--odom-topic", metavar="TOPIC",
                        help="mapping/odometry/topic: nav_msgs/Odometry in the bag whose poses link consecutive "
                             "stations (long walks; docs/mapping.md)")
    parser.add_argument("--odom-extrinsics", metavar="'X Y Z RX RY RZ'",
                        help="mapping/odometry/base_to_odom: pose of the odometry's body frame (child_frame_id) in "
                             "the ring's base frame, m and rotation vector in rad (TagSLAM's T_body_odom)")
    parser.add_argument("--no-surveyed-unseen", action="store_true",
                        help="mapping/surveyed_unseen: false: surveyed markers (--anchors with a full pose) that the "
                             "bag never shows are left out of the map instead of placed from the survey alone")
    parser.add_argument("--progress", action="store_true", help="progress bar on stderr even when it is not a terminal")


def load_config(args: argparse.Namespace) -> MapperConfig:
    """The mapper's parameters from ``--config`` (or the package's file) with the options applied."""
    from ..ros.bag_source import package_file

    path = args.config or package_file("config", "mapping.yaml")
    return load_yaml_config(MapperConfig, path, {
        "map.method": args.method, "map.reference_marker": args.reference_marker,
        "markers.fiducial_len": args.fiducial_len, "markers.fiducial_len_override": args.fiducial_len_override,
        "input.ignore_fiducials": args.ignore_fiducials, "input.slop": args.slop, "map.map_frame": args.map_frame,
        "map.anchors_file": args.anchors, "map.boards_file": getattr(args, "boards", None),
        "mapping.frame": args.frame, "mapping.odometry.topic": getattr(args, "odom_topic", None),
        "mapping.surveyed_unseen": False if getattr(args, "no_surveyed_unseen", False) else None,
        "mapping.odometry.base_to_odom": _six_numbers(getattr(args, "odom_extrinsics", None), "--odom-extrinsics")})


def _six_numbers(text: Optional[str], option: str) -> Optional[List[float]]:
    """``"x y z rx ry rz"`` (spaces or commas) as 6 floats; None when the option is not given."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) != 6 or not all(np.isfinite(values)):
        raise ConfigError(f"expected 6 numbers 'x y z rx ry rz' (m, rad), got {text!r}", key=option)
    return values


def run(args: argparse.Namespace) -> int:
    try:
        from ..ros.bag_source import BagSource, package_file
    except ImportError as exc:
        sys.stderr.write(f"build-map: needs the ROS Python packages (rosbag; source .ws/env.sh): {exc}\n")
        return 2
    if args.update:
        return run_update(args)
    if not args.out:
        raise ConfigError("--out is required (unless --update MAP)")
    if args.markers:
        raise ConfigError("--markers goes with --update MAP")
    config = load_config(args)
    ring = CameraRing.load(args.ring or config.ring_file or package_file("config", "ring.yaml"))
    pipeline = MappingPipeline(config, ring)
    with BagSource(args.bag, ring, progress=args.progress or None) as source:
        source.run(pipeline, command="build-map")
    if not pipeline.frames:
        raise ConfigError("no usable ring frame in the bag (see the lines above)", path=args.bag)
    m = pipeline.save(args.out)
    _print_summary(pipeline, m, args.out)
    return 0


def run_update(args: argparse.Namespace) -> int:
    """``--update MAP --markers ID ...`` (module docstring)."""
    from ..config import load_yaml_config as load
    from ..marker_check import parse_marker_ids
    from ..marker_map import MarkerMap
    from ..pipeline import LocalizationPipeline
    from ..ros.bag_source import BagSource, package_file
    from ..schemas import LocalizerConfig

    try:
        ids = parse_marker_ids(args.markers or [])
    except ValueError as exc:
        raise ConfigError(str(exc), key="--markers") from None
    if not ids:
        raise ConfigError("--update needs --markers ID ... (the markers to re-map)", key="--markers")
    marker_map = MarkerMap.load(args.update)
    missing = [i for i in ids if i not in marker_map]
    if missing:
        raise ConfigError(f"markers {missing} are not in the map (it has {marker_map.ids})", path=args.update,
                          key="--markers")
    if len(marker_map) - len(set(ids)) < 2:
        raise ConfigError("fewer than 2 markers would stay fixed: build a new map instead", path=args.update)
    config = load(LocalizerConfig, args.config or package_file("config", "localization.yaml"), {
        "map_file": args.update, "marker_check.enabled": True, "marker_check.remap_window": 1e9,
        "input.ignore_fiducials": args.ignore_fiducials, "input.slop": args.slop})
    ring = CameraRing.load(args.ring or config.ring_file or package_file("config", "ring.yaml"))
    pipeline = LocalizationPipeline(config, ring, marker_map)
    pipeline.marker_check.excluded = set(ids)
    with BagSource(args.bag, ring, progress=args.progress or None) as source:
        source.run(pipeline, command="build-map --update")
    old = {i: marker_map[i].T_map_marker[:3, 3].copy() for i in ids}
    results = pipeline.remap_markers(ids)
    failed = [why for _, _, why in results if why]
    if failed:
        raise ConfigError("; ".join(failed), path=args.bag)
    out = args.out or args.update
    pipeline.save_map(out)
    sys.stdout.write(f"map: {out} (markers {ids} re-mapped from {args.bag}, {len(marker_map) - len(ids)} others "
                     f"fixed; previous version kept as {out}.bak)\n")
    for mid, moved, _ in results:
        t = marker_map[mid].T_map_marker[:3, 3]
        sys.stdout.write(f"{mid:>6} moved {100 * moved:6.1f} cm: ({old[mid][0]:.3f}, {old[mid][1]:.3f}, "
                         f"{old[mid][2]:.3f}) -> ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, "
                         f"{marker_map[mid].observations // 4} views, RMS {marker_map[mid].rms_px:.2f} px\n")
    return 0


def _print_summary(pipeline: MappingPipeline, m, path: str) -> None:
    s = pipeline.summary()
    out = sys.stdout
    if m.anchors is not None:
        out.write(f"map: {path} ({m.method}, frame '{m.frame_id}' (survey, {m.anchors['kind']}): "
                  f"{m.frame_definition})\n")
    else:
        out.write(f"map: {path} ({m.method}, frame '{m.frame_id}' ({m.frame_convention}), reference marker "
                  f"{m.reference_marker})\n")
    out.write(f"frames {s['frames']}, stations {s['linked_stations']}/{s['stations']} ({s['station_model']})\n")
    out.write(f"{'id':>6} {'x (m)':>9} {'y (m)':>9} {'z (m)':>9} {'std (mm)':>9} {'obs':>6}\n")
    for e in m:
        t = e.T_map_marker[:3, 3]
        out.write(f"{e.marker_id:>6} {t[0]:>9.3f} {t[1]:>9.3f} {t[2]:>9.3f} "
                  f"{1000 * float(np.max(e.position_std)):>9.2f} {e.observations:>6}"
                  f"{'  surveyed only' if e.surveyed_only else ''}\n")
    if m.surveyed_only_ids:
        out.write(f"surveyed only: {len(m.surveyed_only_ids)} surveyed marker(s) the bag never shows, in the map at "
                  f"their surveyed pose with the survey's std (flagged surveyed_only; --no-surveyed-unseen leaves "
                  f"them out): {m.surveyed_only_ids}\n")
    if s.get("surveyed_not_mapped"):
        out.write(f"WARNING: surveyed marker(s) the bag never shows and that are NOT in the map (a surveyed position "
                  f"alone cannot place a marker's orientation, or --no-surveyed-unseen): "
                  f"{s['surveyed_not_mapped']}\n")
    if s["ambiguous"]:
        out.write(f"seen from one viewpoint only, orientation ambiguous (mapped with the better solution and a "
                  f"large uncertainty; another view fixes it): {s['ambiguous']}\n")
    warning = pipeline.builder.format_unmapped(m, multiline=True)
    if warning:
        out.write(warning + "\n")
    if m.anchors is not None:
        out.write(f"{'anchor':>6} {'dx (mm)':>9} {'dy (mm)':>9} {'dz (mm)':>9} {'sigmas':>9}\n")
        for p in m.anchors["points"]:
            if p.get("surveyed_only"):
                out.write(f"{p['marker']:>6} never detected: placed from the survey alone\n")
                continue
            if "residual" not in p:
                out.write(f"{p['marker']:>6} not mapped\n")
                continue
            r = 1000 * np.asarray(p["residual"])
            out.write(f"{p['marker']:>6} {r[0]:>9.2f} {r[1]:>9.2f} {r[2]:>9.2f} {p['residual_sigmas']:>9.2f}\n")
    for line in measurement_lines(m.quality.get("survey_measurements")):
        out.write(line + "\n")
    ba = pipeline.last_ba
    if ba is not None and m.method == "refined":
        out.write(f"bundle adjustment: RMS {ba.rms_px_before:.3f} -> {ba.rms_px_after:.3f} px, {ba.seconds:.2f} s\n")
