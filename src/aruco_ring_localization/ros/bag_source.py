"""The one bag source: a recorded bag replayed into a pipeline, as the nodes would have seen it.

``aruco_ring build-map`` and ``aruco_ring localize`` both read bags through :class:`BagSource`,
which feeds :class:`pipeline.MappingPipeline` or :class:`pipeline.LocalizationPipeline` with
the events the node gets, in the bag's order, with ``now`` = each message's receive time:

* per ring camera, whose topics live under its ``namespace`` (written ``ring/cam0``,
  ``/ring/cam0`` or ``ring/cam0/`` in the ring file: all the same): the detections, from the
  best-ranked topic of a type in :data:`DETECTION_CONVERTERS` (``fiducial_vertices`` first, then
  AprilTag detections, ``apriltag_msgs/ApriltagArrayStamped`` or ``apriltag_ros/AprilTagDetectionArray``
  (:mod:`.apriltag`: message classes from the bag's stored definitions), else raw or compressed
  images run through the detector node's core), and ``camera_info``;
* ``cmd_vel`` and ``odom`` (localization: the gate's motion input);
* extrinsics, with ``input/use_tf`` (the default): from ``/tf_static`` for each camera the bag
  has ``<base_frame> -> <camera frame>`` for, else the ring file's (the same rule for both
  commands; the summary says which camera got what). Intrinsics: each camera's camera_info,
  else the ring file's (said too).

Adding a detection message type is one entry in :data:`DETECTION_CONVERTERS` (a function of the
message and the camera's :class:`CameraContext`, returning observations in aruco_detect's corner
order). A tqdm progress bar (ring frames, with their rate) goes to stderr on a terminal or with
``progress=True``; rospy/rosbag INFO lines are silenced.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import sys
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..camera import CameraModel
from ..config import load_config
from ..detections import MarkerObservation
from ..errors import ArucoRingError, ConfigError
from ..ring import CameraRing
from ..schemas import DetectorConfig
from .apriltag import APRILTAG_MSGS_TYPE, APRILTAG_ROS_TYPE, apriltag_msgs_to_observations, apriltag_ros_to_observations
from .conversions import (camera_info_to_model, fiducial_array_to_observations, make_transform_stamped, msg_to_transform,
                          pose_msg_to_transform, stamp_to_sec)

logger = logging.getLogger(__name__)

PACKAGE = "aruco_ring_localization"


def package_file(*parts: str) -> str:
    """A file of the package (``config/ring.yaml``): its share directory, or this source tree's."""
    try:
        import rospkg

        return os.path.join(rospkg.RosPack().get_path(PACKAGE), *parts)
    except Exception:  # noqa: BLE001 - rospkg raises its own types when the package is not on ROS_PACKAGE_PATH
        here = os.path.dirname(os.path.abspath(__file__))
        return os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(here))), *parts)


@dataclass
class CameraContext:
    """What a converter may need about the camera whose message it converts."""

    name: str
    model: Optional[CameraModel] = None       # its intrinsics in force (camera_info or ring file)
    detector_config: Optional[DetectorConfig] = None
    _detector: Any = None

    def detector(self):
        """The detector node's core for this camera (made on first use)."""
        if self._detector is None:
            from .detector import DetectorCore

            self._detector = DetectorCore(self.detector_config or DetectorConfig(), name=self.name)
        return self._detector


@dataclass(frozen=True)
class DetectionConverter:
    """How one message type becomes a camera's detections.

    Attributes:
        convert: ``(msg, CameraContext) -> observations`` (raw pixels, aruco_detect corner order),
            or None when the message gives nothing to pass on (an unusable image).
        rank: when a camera has topics of several such types, the lowest rank is replayed.
        what: how the summary names the source.
    """

    convert: Callable[[Any, CameraContext], Optional[List[MarkerObservation]]]
    rank: int
    what: str


def _from_fiducials(msg, _ctx: CameraContext) -> List[MarkerObservation]:
    return fiducial_array_to_observations(msg)


def _from_apriltag_msgs(msg, _ctx: CameraContext) -> List[MarkerObservation]:
    return [o for obs in apriltag_msgs_to_observations(msg).values() for o in obs]


def _from_apriltag_ros(msg, ctx: CameraContext) -> List[MarkerObservation]:
    # The tags' corners projected from apriltag_ros's poses through the camera's intrinsics in force.
    return [o for obs in apriltag_ros_to_observations(msg, lambda _frame: ctx.model).values() for o in obs]


def _from_image(msg, ctx: CameraContext) -> Optional[List[MarkerObservation]]:
    det = ctx.detector().on_image(msg)
    return None if det is None else det.observations


#: message type -> converter. One entry per supported detection type.
DETECTION_CONVERTERS: Dict[str, DetectionConverter] = {
    "fiducial_msgs/FiducialArray": DetectionConverter(_from_fiducials, 0, "fiducial_vertices"),
    APRILTAG_MSGS_TYPE: DetectionConverter(_from_apriltag_msgs, 10, "AprilTag corners (apriltag_msgs)"),
    APRILTAG_ROS_TYPE: DetectionConverter(_from_apriltag_ros, 11, "AprilTag poses projected (apriltag_ros)"),
    "sensor_msgs/Image": DetectionConverter(_from_image, 20, "images through the detector"),
    "sensor_msgs/CompressedImage": DetectionConverter(_from_image, 21, "compressed images through the detector"),
}

#: Topic names that carry images that are not the camera's own (the detector's annotated output).
_NOT_CAMERA_IMAGES = ("fiducial_images",)


def _norm(name: str) -> str:
    return "/".join(p for p in str(name).split("/") if p)


@dataclass
class BagPlan:
    """What a bag holds for a ring, and where each input comes from (topics as the bag spells them;
    one name written ``/ns/x`` and ``ns/x`` in the same bag gives two topics, both replayed)."""

    detections: Dict[str, Tuple[List[str], str]] = field(default_factory=dict)  # camera -> (topics, msg type)
    camera_info: Dict[str, List[str]] = field(default_factory=dict)              # camera -> topics
    motion: Dict[str, List[str]] = field(default_factory=dict)                   # cmd_vel / odom -> topics
    tf_static: List[str] = field(default_factory=list)
    counts: Dict[str, int] = field(default_factory=dict)                         # topic -> messages

    def count(self, topics: Sequence[str]) -> int:
        return sum(self.counts[t] for t in topics)


def plan_topics(topics: Dict[str, Tuple[str, int]], ring: CameraRing, cameras: Sequence[str]) -> BagPlan:
    """Match a bag's topics (``{topic: (type, count)}``) to the ring's cameras and the motion inputs."""
    plan = BagPlan(counts={t: n for t, (_, n) in topics.items()})
    by_norm: Dict[Tuple[str, str], List[str]] = {}
    for t, (typ, _) in sorted(topics.items()):
        by_norm.setdefault((_norm(t), typ), []).append(t)
    for camera in cameras:
        ns = _norm(ring[camera].namespace)
        prefix = f"{ns}/" if ns else ""
        best = None
        for (norm, typ), raw in by_norm.items():
            conv = DETECTION_CONVERTERS.get(typ)
            rest = norm[len(prefix):] if norm.startswith(prefix) else None
            if conv is None or not rest or rest.split("/")[0] in _NOT_CAMERA_IMAGES:
                continue
            if prefix == "" and "/" in rest:
                continue  # without a namespace only the top-level topics are the camera's
            key = (conv.rank, rest.count("/"), rest)
            if best is None or key < best[0]:
                best = (key, raw, typ)
        if best is not None:
            plan.detections[camera] = (best[1], best[2])
        info = by_norm.get((f"{prefix}camera_info", "sensor_msgs/CameraInfo"))
        if info:
            plan.camera_info[camera] = info
    for source, typ in (("cmd_vel", "geometry_msgs/Twist"), ("odom", "nav_msgs/Odometry")):
        if by_norm.get((source, typ)):
            plan.motion[source] = by_norm[(source, typ)]
    plan.tf_static = by_norm.get(("tf_static", "tf2_msgs/TFMessage"), [])
    return plan


def _quiet_ros_logging() -> None:
    """No rospy / rosbag INFO noise offline (their loggers propagate to the command's root logger)."""
    for name in ("rospy", "rosout", "rosbag", "roslib", "genpy", "rosgraph"):
        logging.getLogger(name).setLevel(logging.WARNING)


class BagSource:
    """A bag, read for one ring (module docstring).

    Args:
        path: the bag file.
        ring: the calibrated ring (camera namespaces and frames, fallback calibration).
        progress: show the progress bar (None: only when stderr is a terminal).
        detector_config: the detector's parameters for image topics (default config/detector.yaml).
        out: where the summary lines go (stderr).

    Raises:
        ConfigError: the bag cannot be opened, or holds no detections of the ring's cameras.
    """

    def __init__(self, path: str, ring: CameraRing, progress: Optional[bool] = None,
                 detector_config: Optional[DetectorConfig] = None, out=None):
        _quiet_ros_logging()
        import rosbag

        self.path = path
        self.ring = ring
        self.out = out or sys.stderr
        self.progress = bool(progress) if progress is not None else self.out.isatty()
        self.detector_config = detector_config
        try:
            self._bag = rosbag.Bag(path)
        except (OSError, rosbag.ROSBagException) as exc:
            raise ConfigError(f"cannot open bag ({exc})", path=path) from None
        info = self._bag.get_type_and_topic_info().topics
        self.topics = {t: (i.msg_type, int(i.message_count)) for t, i in info.items()}

    def close(self) -> None:
        self._bag.close()

    def __enter__(self) -> "BagSource":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    # --- inputs -------------------------------------------------------------------------------

    def static_extrinsics(self, topics: Sequence[str]) -> Dict[str, np.ndarray]:
        """camera -> ``T_base_cam`` from the bag's ``/tf_static`` (``<base_frame> -> <camera frame>``; last wins)."""
        out: Dict[str, np.ndarray] = {}
        base = self.ring.base_frame
        for topic, msg, _ in self._bag.read_messages(topics=list(topics)):
            for ts in msg.transforms:
                cam = self.ring.by_frame(ts.child_frame_id)
                if cam is None or _norm(ts.header.frame_id) != base:
                    continue
                try:
                    out[cam.name] = msg_to_transform(ts.transform, f"{topic} {base} -> {ts.child_frame_id}")
                except ArucoRingError as exc:
                    self.say(f"{topic}: {exc}; ignored")
        return out

    def say(self, text: str) -> None:
        self.out.write(text + "\n")
        self.out.flush()

    def _detector_config(self) -> DetectorConfig:
        if self.detector_config is not None:
            return self.detector_config
        path = package_file("config", "detector.yaml")
        if not os.path.isfile(path):
            return DetectorConfig()
        import yaml

        with open(path, encoding="utf-8") as fh:
            return load_config(DetectorConfig, yaml.safe_load(fh) or {}, source=path)

    # --- replay -------------------------------------------------------------------------------

    def run(self, pipeline, command: str = "aruco_ring") -> list:
        """Replay the bag into ``pipeline``; returns what its calls returned (poses for localization).

        The pipeline gets, before the first message, each camera's extrinsics (``/tf_static`` or
        the ring file's, when ``input/use_tf``) and the ring file's intrinsics for cameras whose
        camera_info the bag lacks; then every message in the bag's order, ``poll(t)`` after each,
        and ``flush`` at the end.
        """
        cameras = pipeline.camera_names
        plan = plan_topics(self.topics, self.ring, cameras)
        if not plan.detections:
            wanted = sorted({f"/{_norm(self.ring[c].namespace)}/fiducial_vertices" for c in cameras})
            raise ConfigError(f"no detections of the ring's cameras: no message on any of {wanted} (nor images "
                              f"under those namespaces); types known: {sorted(DETECTION_CONVERTERS)}",
                              path=self.path)
        self._set_calibration(pipeline, plan)
        contexts = {c: CameraContext(c, pipeline.input.camera_model(c), None) for c in cameras}
        if any(typ != "fiducial_msgs/FiducialArray" for _, typ in plan.detections.values()):
            # Only the corners are replayed: no marker poses, no annotated images.
            dconf = dataclasses.replace(self._detector_config(), do_pose_estimation=False, publish_images=False)
            for ctx in contexts.values():
                ctx.detector_config = dconf
        kinds: Dict[str, Tuple[str, str]] = {}
        for cam, (topics, typ) in plan.detections.items():
            kinds.update({t: ("det", cam) for t in topics})
        for cam, topics in plan.camera_info.items():
            kinds.update({t: ("info", cam) for t in topics})
        for source, topics in plan.motion.items():
            kinds.update({t: ("motion", source) for t in topics})
        odom_topic = str(getattr(pipeline, "odometry_topic", "") or "")
        if odom_topic:
            # mapping.odometry.topic: the robot's odometry links the mapping's stations.
            found = [t for t, (typ, _) in self.topics.items() if _norm(t) == _norm(odom_topic)]
            odoms = sorted(t for t, (typ, _) in self.topics.items() if typ == "nav_msgs/Odometry")
            if not found or any(self.topics[t][0] != "nav_msgs/Odometry" for t in found):
                raise ConfigError(f"mapping/odometry/topic {odom_topic}: no nav_msgs/Odometry on it in the bag "
                                  f"(nav_msgs/Odometry topics there: {odoms or 'none'})", path=self.path)
            kinds.update({t: ("odometry", t) for t in found})
            self.say(f"{command}: odometry from {' '.join(found)} ({plan.count(found)} messages)")
        for cam, (topics, typ) in sorted(plan.detections.items()):
            self.say(f"{command}: {cam}: {DETECTION_CONVERTERS[typ].what} from {' '.join(topics)} "
                     f"({plan.count(topics)} messages)")
        total = max(plan.count(t) for t, _ in plan.detections.values())
        bar = self._progress_bar(total)
        outputs: list = []
        frames_before = pipeline.input.ring_frames_out
        t = 0.0
        try:
            for topic, msg, stamp in self._bag.read_messages(topics=sorted(kinds)):
                kind, name = kinds[topic]
                t = stamp.to_sec()
                try:
                    res = self._dispatch(pipeline, kind, name, msg, t, contexts)
                    if res:
                        outputs.append(res)
                    res = pipeline.poll(t)
                    if res:
                        outputs.append(res)
                except ArucoRingError as exc:
                    pipeline.warn(f"{topic}.error", f"{command}: {topic} at {t:.3f} s: {exc}", t)
                if bar is not None:
                    done = pipeline.input.ring_frames_out - frames_before
                    if done > bar.n:
                        bar.update(done - bar.n)
            res = pipeline.flush(t)
            if res:
                outputs.append(res)
        finally:
            if bar is not None:
                bar.close()
        return [o for res in outputs for o in (res if isinstance(res, list) else [res])]

    def _set_calibration(self, pipeline, plan: BagPlan) -> None:
        cameras = pipeline.camera_names
        p = pipeline.input.params
        if p.use_tf:
            tf = self.static_extrinsics(plan.tf_static) if plan.tf_static else {}
            for cam in cameras:
                pipeline.on_extrinsics(cam, tf.get(cam))
            from_tf = [c for c in cameras if c in tf]
            others = [c for c in cameras if c not in tf]
            self.say(f"extrinsics: {len(from_tf)} cameras from /tf_static ({self.ring.base_frame} -> camera frame)"
                     f"{': ' + ' '.join(from_tf) if from_tf else ''}; {len(others)} from the ring file"
                     f"{': ' + ' '.join(others) if others else ''}")
        else:
            self.say("extrinsics: from the ring file (input/use_tf is false)")
        missing = [c for c in cameras if c not in plan.camera_info]
        for cam in missing:
            pipeline.on_camera_info(cam, self.ring[cam].model)
        self.say(f"intrinsics: {len(cameras) - len(missing)} cameras from camera_info; {len(missing)} from the ring "
                 f"file (no camera_info in the bag){': ' + ' '.join(missing) if missing else ''}")

    def _dispatch(self, pipeline, kind: str, name: str, msg, t: float, contexts: Dict[str, CameraContext]):
        if kind == "det":
            ctx = contexts[name]
            typ = msg._type
            obs = DETECTION_CONVERTERS[typ].convert(msg, ctx)
            if obs is None:
                return None
            return pipeline.on_detections(name, stamp_to_sec(msg.header.stamp), obs, t)
        if kind == "info":
            model = camera_info_to_model(msg, name=name)
            if contexts[name].model is None or not _same_model(contexts[name].model, model):
                contexts[name].model = model
                pipeline.on_camera_info(name, model)
            return None
        if kind == "odometry":
            T = pose_msg_to_transform(msg.pose.pose, f"{name} pose.pose")
            stamp = stamp_to_sec(msg.header.stamp)
            pipeline.on_odometry(stamp if stamp > 0 else t, T)
            return None
        if not hasattr(pipeline, "on_motion"):
            return None
        if name == "cmd_vel":
            return pipeline.on_motion("cmd_vel", None, (msg.linear.x, msg.linear.y), msg.angular.z, t)
        tw = msg.twist.twist
        try:   # as the node: with motion.odometry the pose predicts the filter; a bad one is not the gate's problem
            T_odom_base = pose_msg_to_transform(msg.pose.pose, "odom.pose.pose")
        except ArucoRingError:
            T_odom_base = None
        return pipeline.on_motion("odom", stamp_to_sec(msg.header.stamp), (tw.linear.x, tw.linear.y), tw.angular.z,
                                  t, T_odom_base)

    def _progress_bar(self, total: int):
        if not self.progress:
            return None
        from tqdm import tqdm

        return tqdm(total=total, unit="frame", file=self.out, dynamic_ncols=True, desc=os.path.basename(self.path))


def _same_model(a: CameraModel, b: CameraModel) -> bool:
    return (a.width, a.height, a.distortion_model) == (b.width, b.height, b.distortion_model) and \
        np.array_equal(a.K, b.K) and np.array_equal(np.asarray(a.D), np.asarray(b.D))


# --- references: a pose topic or a tf chain of a bag, for aruco_ring export-tum ------------------

#: Pose message types a reference topic may carry -> the Pose inside (with its field name).
POSE_FIELDS: Dict[str, Tuple[Callable[[Any], Any], str]] = {
    "geometry_msgs/PoseStamped": (lambda m: m.pose, "pose"),
    "geometry_msgs/PoseWithCovarianceStamped": (lambda m: m.pose.pose, "pose.pose"),
    "nav_msgs/Odometry": (lambda m: m.pose.pose, "pose.pose"),
}


def read_reference(path: str, topic: Optional[str] = None, tf: Optional[Tuple[str, str]] = None,
                   progress: Optional[bool] = None, out=None) -> Tuple[np.ndarray, np.ndarray, str]:
    """A reference trajectory from a bag: ``(stamps, T_parent_child (N, 4, 4), what)``.

    ``topic``: every message of a :data:`POSE_FIELDS` type, at its header stamp (its receive time
    when the stamp is zero). ``tf = (parent, child)``: the chain parent -> ... -> child through
    ``/tf`` and ``/tf_static`` (tf2's buffer, the whole bag cached), at each stamp of a ``/tf``
    transform on the way, skipping stamps the chain does not cover yet (before its first
    transform). Exactly one of the two. A progress bar (messages) goes to stderr on a terminal or
    with ``progress=True``; bad messages are skipped and counted in ``what``.

    Raises:
        ConfigError: the bag cannot be opened, the topic is missing or of another type, or no pose.
    """
    _quiet_ros_logging()
    import rosbag

    if (topic is None) == (tf is None):
        raise ConfigError("give a pose topic or a tf chain (parent, child), not both or neither")
    out = out or sys.stderr
    show = bool(progress) if progress is not None else out.isatty()
    try:
        bag = rosbag.Bag(path)
    except (OSError, rosbag.ROSBagException) as exc:
        raise ConfigError(f"cannot open bag ({exc})", path=path) from None
    with bag:
        topics = {t: (i.msg_type, int(i.message_count)) for t, i in bag.get_type_and_topic_info().topics.items()}
        if topic is not None:
            return _poses_from_topic(bag, path, topics, topic, show, out)
        return _poses_from_tf(bag, path, topics, tf, show, out)


def _reference_bar(show: bool, total: int, out, path: str):
    if not show:
        return None
    from tqdm import tqdm

    return tqdm(total=total, unit="msg", file=out, dynamic_ncols=True, desc=os.path.basename(path))


def _poses_from_topic(bag, path: str, topics, topic: str, show: bool, out):
    name = topic if topic in topics else ("/" + topic.lstrip("/") if "/" + topic.lstrip("/") in topics else None)
    if name is None:
        posed = sorted(t for t, (typ, _) in topics.items() if typ in POSE_FIELDS)
        raise ConfigError(f"no topic {topic} in the bag; pose topics there: {posed or 'none'}", path=path)
    typ = topics[name][0]
    if typ not in POSE_FIELDS:
        raise ConfigError(f"{name} is {typ}, not one of {sorted(POSE_FIELDS)}", path=path)
    get, field_name = POSE_FIELDS[typ]
    from .conversions import pose_msg_to_transform

    stamps, poses, bad = [], [], 0
    bar = _reference_bar(show, topics[name][1], out, path)
    try:
        for _, msg, t in bag.read_messages(topics=[name]):
            if bar is not None:
                bar.update(1)
            try:
                T = pose_msg_to_transform(get(msg), f"{name} {field_name}")
            except ArucoRingError as exc:
                bad += 1
                logger.debug("%s", exc)
                continue
            s = stamp_to_sec(msg.header.stamp)
            stamps.append(s if s > 0 else t.to_sec())
            poses.append(T)
    finally:
        if bar is not None:
            bar.close()
    return _finish(path, stamps, poses, bad, f"{name} ({typ})")


def _poses_from_tf(bag, path: str, topics, tf: Tuple[str, str], show: bool, out):
    import rospy
    import tf2_py

    parent, child = (_norm(f) for f in tf)
    tf_topics = [t for t in ("/tf", "/tf_static") if t in topics]
    if "/tf" not in topics and "/tf_static" not in topics:
        raise ConfigError("no /tf nor /tf_static in the bag", path=path)
    msgs = list(bag.read_messages(topics=tf_topics))
    if not msgs:
        raise ConfigError("/tf and /tf_static are empty", path=path)
    span = msgs[-1][2].to_sec() - msgs[0][2].to_sec()
    core = tf2_py.BufferCore(rospy.Duration(span + 3600.0))
    frames, stamps = set(), set()
    for topic, msg, _ in msgs:
        for raw in msg.transforms:
            names = (_norm(raw.header.frame_id), _norm(raw.child_frame_id))
            try:
                # tf2 wants geometry_msgs types, not the bag's own classes; invalid ones are skipped
                ts = make_transform_stamped(msg_to_transform(raw.transform, f"{topic} {names[0]} -> {names[1]}"),
                                            names[0], names[1], rospy.Time(raw.header.stamp.secs, raw.header.stamp.nsecs))
                if topic == "/tf_static":
                    core.set_transform_static(ts, "bag")
                else:
                    core.set_transform(ts, "bag")
                    stamps.add(ts.header.stamp.to_nsec())
            except (ArucoRingError, tf2_py.TransformException) as exc:
                logger.debug("%s: %s", topic, exc)
                continue
            frames.update(names)
    for f in (parent, child):
        if f not in frames:
            raise ConfigError(f"no frame {f} in the bag's tf; frames there: {sorted(frames)}", path=path)
    out_stamps, poses, bad = [], [], 0
    bar = _reference_bar(show, len(stamps), out, path)
    try:
        for ns in sorted(stamps):
            if bar is not None:
                bar.update(1)
            try:
                ts = core.lookup_transform_core(parent, child, rospy.Time(nsecs=ns))
            except tf2_py.TransformException:
                continue   # not on the chain, or outside the chain's time range
            try:
                poses.append(msg_to_transform(ts.transform, f"tf {parent} -> {child}"))
            except ArucoRingError:
                bad += 1
                continue
            out_stamps.append(ns * 1e-9)
    finally:
        if bar is not None:
            bar.close()
    if not poses:
        raise ConfigError(f"tf {parent} -> {child}: no stamp where the chain is complete (are the frames "
                          f"connected? frames in the bag: {sorted(frames)})", path=path)
    return _finish(path, out_stamps, poses, bad, f"tf {parent} -> {child}")


def _finish(path: str, stamps, poses, bad: int, what: str):
    if not poses:
        raise ConfigError(f"{what}: no valid pose" + (f" ({bad} invalid)" if bad else ""), path=path)
    s = np.asarray(stamps, dtype=np.float64)
    order = np.argsort(s, kind="stable")
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = np.diff(s[order]) > 0       # one pose per stamp (TUM: strictly increasing)
    idx = order[keep]
    text = f"{what}: {len(idx)} poses" + (f", {bad} invalid messages skipped" if bad else "")
    return s[idx], np.stack(poses)[idx], text
