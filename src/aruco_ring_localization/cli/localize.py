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

``--smooth``: a **smoothed trajectory** (post-processing a recording, :mod:`smoother`): every ring
frame's pose from all the frames' corners and the robot's odometry between consecutive frames at
once (one batch problem, as TagSLAM's rig poses), the map and the ring held; started from the
filtered output. The odometry: ``--odom-topic`` (nav_msgs/Odometry or any pose topic), its body's
pose in the ring's base frame ``--odom-extrinsics`` (TagSLAM's ``T_body_odom``) and the links'
noise model from the mapper's ``mapping.odometry`` section (``--odom-config``, default
config/mapping.yaml: the package's defaults), or all three from a tagslam.yaml's rig body
(``--odom-tagslam``: the problem as the file states it, its odometry noise judged at the frames as
TagSLAM's synchronizer pairs them, and weighed against its corner noise, ``pixel_noise``, in place
of ``estimator/pixel_noise``). Frames without a mapped marker are posed by the odometry where it links
them. Without odometry there is nothing to smooth with: the smoothed trajectory would be the
per-frame estimate (``--output measurement``), and the command says so.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
from typing import List, Tuple

import numpy as np

from .. import geometry as geo
from ..config import load_yaml_config
from ..errors import ConfigError
from ..evaluation.trajectories import trajectory, write_tum
from ..fileio import atomic_write_text
from ..mapping_odometry import MappingOdometryOptions
from ..marker_map import MarkerMap
from ..pipeline import LocalizationPipeline, PoseOutput, TrackResult
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
    sm = parser.add_argument_group("smoothing (--smooth: post-processing a whole recording with its odometry)")
    sm.add_argument("--smooth", action="store_true",
                    help="a smoothed trajectory: every ring frame's pose from all the frames' corners and the "
                         "odometry between consecutive frames at once (map and ring held), started from the "
                         "filtered output; needs the bag's odometry (--odom-topic)")
    sm.add_argument("--odom-topic", metavar="TOPIC",
                    help="the odometry in the bag (nav_msgs/Odometry, or any pose topic): its poses link consecutive "
                         "frames (default: --odom-config's mapping/odometry/topic)")
    sm.add_argument("--odom-extrinsics", metavar="'X Y Z RX RY RZ'",
                    help="pose of the odometry's body frame (child_frame_id) in the ring's base frame, m and rotation "
                         "vector in rad (TagSLAM's T_body_odom; default: --odom-config's base_to_odom)")
    sm.add_argument("--odom-config", metavar="FILE",
                    help="a mapper parameter file whose mapping/odometry section gives the links' noise model "
                         "(default: config/mapping.yaml, the package's defaults)")
    sm.add_argument("--odom-tagslam", metavar="TAGSLAM_YAML",
                    help="topic, T_body_odom and noise (odom_acceleration ...) of the odometry of the tagslam.yaml "
                         "body named as the ring's base frame, judged at the frames (one message per frame, as "
                         "TagSLAM's synchronizer pairs them), in place of --odom-config's; and the corner noise "
                         "they are weighed against, the file's pixel_noise, in place of estimator/pixel_noise")
    sm.add_argument("--level", action="store_true",
                    help="a ground robot: every smoothed pose's z axis held along the map's (roll, pitch ~0)")


def load_config(args: argparse.Namespace) -> LocalizerConfig:
    """The node's parameters from ``--config`` (or the package's file) with the options applied."""
    from ..ros.bag_source import package_file

    path = args.config or package_file("config", "localization.yaml")
    return load_yaml_config(LocalizerConfig, path, {
        "map_file": args.map_file, "estimator.fusion": args.fusion, "input.slop": args.slop,
        "input.ignore_fiducials": args.ignore_fiducials,
        "filter.model": getattr(args, "filter_model", None) or ("6dof" if getattr(args, "six_dof", False) else None)})


class _RecordingPipeline(LocalizationPipeline):
    """The localizer's pipeline that also keeps every ring frame it is given and its track (the
    smoother's input and start)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.recorded_frames: list = []
        self.recorded_tracks: dict = {}

    def _process(self, frames, now):
        self.recorded_frames.extend(frames)
        return super()._process(frames, now)

    def _track(self, ring_frame) -> TrackResult:
        track = super()._track(ring_frame)
        self.recorded_tracks[id(ring_frame)] = track
        return track


def odometry_options(args: argparse.Namespace, ring: CameraRing) -> Tuple[MappingOdometryOptions, str]:
    """The odometry links' settings for ``--smooth`` and where they come from (said to the user)."""
    from ..importers.tagslam import tagslam_odometry
    from ..ros.bag_source import package_file
    from ..schemas import MapperConfig
    from .build_map import _six_numbers

    path = args.odom_config or package_file("config", "mapping.yaml")
    opts = load_yaml_config(MapperConfig, path).mapping.odometry
    source = f"{path} (mapping/odometry{'' if args.odom_config else ': the package defaults'})"
    if args.odom_tagslam:
        found = tagslam_odometry(args.odom_tagslam, ring.base_frame)
        if found is None:
            raise ConfigError(f"no body {ring.base_frame!r} (the ring's base frame) with an odom_topic",
                              path=args.odom_tagslam)
        opts = dataclasses.replace(opts, topic=found.topic, base_to_odom=found.base_to_odom,
                                   **found.stated_link_noise())
        source = f"{args.odom_tagslam} (body {ring.base_frame}: odom_topic, T_body_odom, odom_* noise at the frames)"
    if args.odom_topic:
        opts = dataclasses.replace(opts, topic=args.odom_topic)
    extr = _six_numbers(args.odom_extrinsics, "--odom-extrinsics")
    if extr is not None:
        opts = dataclasses.replace(opts, base_to_odom=tuple(extr))
    return opts, source


def smoother_pixel_noise(args: argparse.Namespace, default: float) -> Tuple[float, str]:
    """The corner noise (px) ``--smooth`` weighs the corners with against the odometry, and where it
    comes from: ``--odom-tagslam``'s ``pixel_noise`` (the odometry's noise is stated against it: on
    TagSLAM's test_11 the smoothed poses were 2.96 mm from its rig poses at the localizer's 0.5 px,
    0.01 mm at the file's 1 px), else the localizer's ``estimator/pixel_noise``."""
    from ..importers.tagslam import tagslam_pixel_noise

    if args.odom_tagslam:
        found = tagslam_pixel_noise(args.odom_tagslam)
        if found is not None:
            return found, f"{args.odom_tagslam}: tagslam_parameters.pixel_noise"
    return default, "estimator/pixel_noise"


def _noise_text(o: MappingOdometryOptions) -> str:
    if o.noise_model == "per_message":
        if o.message_translation_noise > 0 and o.message_rotation_noise > 0:
            return (f"per_message, fixed {o.message_translation_noise:g} m / {o.message_rotation_noise:g} rad per "
                    f"message")
        return (f"per_message, acceleration {o.message_acceleration:g} m/s^2 (max "
                f"{o.message_acceleration_max or 10 * o.message_acceleration:g}), angular "
                f"{o.message_angular_acceleration:g} rad/s^2 (max "
                f"{o.message_angular_acceleration_max or 10 * o.message_angular_acceleration:g})")
    return (f"random_walk, {o.translation_noise:g} m/sqrt(m), {o.rotation_noise:g} rad/sqrt(rad), "
            f"{o.rotation_per_metre:g} rad/sqrt(m), floors {o.min_translation:g} m / {o.min_rotation:g} rad")


def run_smooth(args: argparse.Namespace) -> int:
    """``--smooth`` (module docstring)."""
    from ..ros.bag_source import POSE_FIELDS, BagSource, package_file, read_reference
    from ..smoother import SmootherOptions, odometry_track, smooth_trajectory

    if args.output != "filtered" or args.csv:
        raise ConfigError("--smooth writes the smoothed poses: --output and --csv do not apply to it")
    config = load_config(args)
    ring = CameraRing.load(args.ring or config.ring_file or package_file("config", "ring.yaml"))
    marker_map = MarkerMap.load(args.map_file)
    odo_opts, odo_source = odometry_options(args, ring)
    with BagSource(args.bag, ring, progress=args.progress or None) as source:
        odoms = sorted(t for t, (typ, _) in source.topics.items() if typ == "nav_msgs/Odometry")
        if not odo_opts.topic:
            raise ConfigError(f"--smooth needs the robot's odometry: --odom-topic TOPIC (nav_msgs/Odometry topics in "
                              f"the bag: {', '.join(odoms) or 'none'}). Without odometry there is nothing to smooth "
                              f"with: the smoothed trajectory would be the per-frame estimate (--output measurement)",
                              path=args.bag)
        named = [t for t in source.topics if t.strip("/") == odo_opts.topic.strip("/")]
        if not named:
            posed = sorted(t for t, (typ, _) in source.topics.items() if typ in POSE_FIELDS)
            raise ConfigError(f"odometry topic {odo_opts.topic}: not in the bag (nav_msgs/Odometry topics there: "
                              f"{', '.join(odoms) or 'none'}; other pose topics: "
                              f"{', '.join(t for t in posed if t not in odoms) or 'none'})", path=args.bag)
        pipeline = _RecordingPipeline(config, ring, marker_map)
        outputs: List[PoseOutput] = source.run(pipeline, command="localize")
    with open(os.devnull, "w", encoding="utf-8") as null:
        o_stamps, o_poses, what = read_reference(args.bag, topic=odo_opts.topic, out=null)
    track = odometry_track(o_stamps, o_poses, topic=odo_opts.topic)
    start_of = {id(out.track): out.T_map_base_6dof for out in outputs if not out.from_odometry}
    frames = pipeline.recorded_frames
    initial = []
    for f in frames:
        tr = pipeline.recorded_tracks.get(id(f))
        T = start_of.get(id(tr)) if tr is not None else None
        if T is None and tr is not None and tr.localization.ok:
            T = tr.localization.T_map_base
        initial.append(T)
    est = config.estimator
    pixel_noise, px_source = smoother_pixel_noise(args, est.pixel_noise)
    res = smooth_trajectory(frames, pipeline.ring, marker_map, track, odo_opts, initial,
                            SmootherOptions(pixel_noise=pixel_noise, reject_px=est.max_reprojection_error,
                                            level=bool(args.level)))
    poses = [T if args.six_dof else geo.transform_from_se2(*geo.se2_from_transform(T), z=T[2, 3])
             for T in res.T_map_base]
    write_tum(args.out, trajectory(list(res.stamps), poses))
    sys.stdout.write(
        f"localize --smooth: {len(frames)} ring frames -> {len(res.stamps)} smoothed poses"
        f"{' (6 dof)' if args.six_dof else ''} written to {args.out}: {int(res.observed.sum())} with a mapped marker, "
        f"{int((~res.observed).sum())} placed by the odometry alone, {res.dropped} left out; odometry {what}, "
        f"{res.links} links (noise: {_noise_text(odo_opts)}; from {odo_source}; base_to_odom "
        f"{list(np.round(odo_opts.base_to_odom, 6))}); corners at {pixel_noise:g} px ({px_source}), {res.rejected} "
        f"observations rejected (> {est.max_reprojection_error:g} px); RMS {res.rms_px_before:.3f} -> "
        f"{res.rms_px_after:.3f} px; {res.cpu_seconds:.2f} s CPU "
        f"({1000.0 * res.cpu_seconds / max(len(res.stamps), 1):.2f} ms per frame)\n")
    return 0


def run(args: argparse.Namespace) -> int:
    try:
        from ..ros.bag_source import BagSource, package_file
    except ImportError as exc:
        sys.stderr.write(f"localize: needs the ROS Python packages (rosbag; source .ws/env.sh): {exc}\n")
        return 2
    try:
        if getattr(args, "smooth", False):
            return run_smooth(args)
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
