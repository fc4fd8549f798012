"""``apriltag_relay`` node: AprilTag detections -> ``<ns>/fiducial_vertices`` of every ring camera.

For each ring camera (``~cameras``, default all) it subscribes to ``<ns>/<name>`` for every name in
``~input_topics`` (default ``tags``, what TagSLAM's detector publishes, and ``tag_detections``,
apriltag_ros's) and accepts on any of them either message type, read by its fields from the
definition the publisher sends (``rospy.AnyMsg``; no apriltag package needs to be installed):

* ``apriltag_msgs/ApriltagArrayStamped``: the corners, AprilTag order converted to aruco_detect's;
* ``apriltag_ros/AprilTagDetectionArray``: the tag's corners projected from its pose through the
  camera model (``<ns>/camera_info`` when it is published, the ring file's otherwise); bundles
  are skipped (:mod:`aruco_ring_localization.ros.apriltag`).

It publishes ``<ns>/fiducial_vertices`` (fiducial_msgs/FiducialArray, as aruco_detect) with the
detection's stamp and the ring camera's ``frame_id`` (what the mapper and the localizer look the
extrinsics up for). A message that cannot be read is logged (throttled) and dropped; the node
never dies on one.

Parameters (private): :class:`aruco_ring_localization.schemas.ApriltagRelayConfig` (docs/parameters.md):
``ring_file``, ``cameras``, ``input_topics``, ``ignore_fiducials``, and the tag sizes the rest of
the pipeline uses, ``fiducial_len`` / ``fiducial_len_override`` or ``tagslam_file`` (a TagSLAM
``tagslam.yaml``): an apriltag_ros detection whose size differs from it is relayed with a warning
(the mapper and the localizer would scale that tag wrongly).
"""
from __future__ import annotations

import sys
from typing import Dict, Optional, Sequence, Tuple

import rospy
from fiducial_msgs.msg import FiducialArray
from sensor_msgs.msg import CameraInfo

from ..camera import CameraModel
from ..errors import ArucoRingError, ConfigError
from ..importers.tagslam import marker_sizes_from
from ..markers import MarkerSizes, parse_id_list
from ..ring import CameraRing
from ..schemas import ApriltagRelayConfig
from .apriltag import APRILTAG_ROS_TYPE, message_class, observations_from_message
from .conversions import camera_info_to_model, observations_to_fiducials
from .params import read_config
from .ring_tf import default_ring_file

WARN_PERIOD = 5.0


class ApriltagRelay:
    """The node's state: one publisher per camera, the message classes seen, the camera models."""

    def __init__(self, ring: CameraRing, cameras: Sequence[str], input_topics: Sequence[str], sizes: MarkerSizes,
                 ignore: Sequence[int] = ()):
        self.ring = ring
        self.sizes = sizes
        self.ignore = frozenset(ignore)
        self._classes: Dict[Tuple[str, str], type] = {}
        self._models: Dict[str, CameraModel] = {}
        self._size_warned: set = set()
        self.relayed = 0
        self.dropped = 0
        self.pubs = {}
        self.subs = []
        for name in cameras:
            cam = ring[name]
            ns = "/" + cam.namespace.strip("/") if cam.namespace.strip("/") else ""
            self.pubs[name] = rospy.Publisher(f"{ns}/fiducial_vertices", FiducialArray, queue_size=10)
            for rel in input_topics:
                self.subs.append(rospy.Subscriber(f"{ns}/{rel.strip('/')}", rospy.AnyMsg, self.on_detections,
                                                  callback_args=name, queue_size=10))
            self.subs.append(rospy.Subscriber(f"{ns}/camera_info", CameraInfo, self.on_camera_info,
                                              callback_args=name, queue_size=1))
        rospy.loginfo("apriltag_relay: %d cameras, inputs %s -> fiducial_vertices", len(self.pubs),
                      ", ".join(s.resolved_name for s in self.subs if not s.resolved_name.endswith("camera_info")))

    def on_camera_info(self, msg: CameraInfo, camera: str) -> None:
        try:
            self._models[camera] = camera_info_to_model(msg, name=camera)
        except ArucoRingError as exc:
            rospy.logwarn_throttle(WARN_PERIOD, f"apriltag_relay: {camera}/camera_info unusable: {exc}")

    def _decode(self, raw: rospy.AnyMsg):
        header = getattr(raw, "_connection_header", None) or {}
        key = (header.get("type", ""), header.get("md5sum", ""))
        cls = self._classes.get(key)
        if cls is None:
            definition = header.get("message_definition", "")
            if not key[0] or not definition:
                raise ArucoRingError("the publisher sent no message type or definition")
            cls = self._classes[key] = message_class(key[0], definition)
        msg = cls()
        msg.deserialize(raw._buff)
        return msg

    def on_detections(self, raw: rospy.AnyMsg, camera: str) -> None:
        cam = self.ring[camera]
        model = self._models.get(camera, cam.model)
        try:
            msg = self._decode(raw)
            per_frame = observations_from_message(msg, lambda _frame: model)
        except (ArucoRingError, ValueError, TypeError, AttributeError) as exc:
            self.dropped += 1
            rospy.logwarn_throttle(WARN_PERIOD, f"apriltag_relay: {camera}: message dropped: {exc}")
            return
        obs = [o for v in per_frame.values() for o in v if o.marker_id not in self.ignore]
        if msg._type == APRILTAG_ROS_TYPE:
            self._check_sizes(msg, camera)
        out = FiducialArray()
        out.header.stamp = msg.header.stamp
        out.header.frame_id = cam.frame_id
        out.image_seq = int(msg.header.seq)
        out.fiducials = observations_to_fiducials(obs)
        self.pubs[camera].publish(out)
        self.relayed += 1

    def _check_sizes(self, msg, camera: str) -> None:
        for det in msg.detections:
            if len(det.id) != 1 or len(det.size) != 1:
                continue
            mid, size = int(det.id[0]), float(det.size[0])
            want = self.sizes(mid)
            if abs(size - want) > 1e-6 * max(want, 1.0) and mid not in self._size_warned:
                self._size_warned.add(mid)
                rospy.logwarn(f"apriltag_relay: {camera}: apriltag_ros says tag {mid} is {size:g} m, the configured "
                              f"size is {want:g} m (fiducial_len / fiducial_len_override / tagslam_file): the mapper "
                              f"and the localizer use the configured one")


def main(argv: Optional[Sequence[str]] = None) -> int:
    rospy.init_node("apriltag_relay", argv=list(argv) if argv is not None else None)
    try:
        params = read_config(ApriltagRelayConfig)
        ring = CameraRing.load(params.ring_file or default_ring_file())
        cameras = list(params.cameras) or ring.names
        unknown = [c for c in cameras if c not in ring.names]
        if unknown:
            raise ConfigError(f"cameras {unknown} are not in the ring ({', '.join(ring.names)})", key="~cameras")
        sizes = marker_sizes_from(params.fiducial_len, params.fiducial_len_override, params.tagslam_file)
        ignore = parse_id_list(params.ignore_fiducials, key="~ignore_fiducials")
    except ConfigError as exc:
        rospy.logfatal(f"apriltag_relay: {exc}")
        return 1
    ApriltagRelay(ring, cameras, params.input_topics, sizes, sorted(ignore))
    rospy.spin()
    return 0


if __name__ == "__main__":
    sys.exit(main())
