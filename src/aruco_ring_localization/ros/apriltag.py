"""AprilTag detection messages -> :class:`~aruco_ring_localization.detections.MarkerObservation`.

Two message types, read by their fields only (duck-typed: no apriltag package is needed, rosbag
and :func:`message_class` build the classes from the definitions a bag or a publisher carries):

* ``apriltag_msgs/ApriltagArrayStamped`` (TagSLAM's detector, versatran01/apriltag_ros):
  ``header``, ``apriltags[]`` with ``id`` and ``corners[4]`` (``geometry_msgs/Point``, pixels of
  the image the detector saw). AprilTag order (counter-clockwise from the tag's bottom-left) is
  converted to aruco_detect's (:data:`markers.APRILTAG_TO_ARUCO`).
* ``apriltag_ros/AprilTagDetectionArray`` (AprilRobotics/apriltag_ros): ``detections[]`` with
  ``id[]``, ``size[]`` and ``pose`` (``T_cam_tag`` from ``cv::solvePnP`` on the four corners with
  the camera_info's pinhole intrinsics and no distortion: apriltag_ros expects rectified images).
  It carries no corners, so the tag's four corners are *projected* from that pose through the
  camera model given (:func:`apriltag_ros_to_observations`): with the ordinary (distorted) camera_info
  of a monocular camera whose ``image_rect`` was detected, that gives the raw-image corners the
  package's pipeline expects. Bundles (``len(id) > 1``) are skipped: their pose is the bundle's.
  The tag frame of apriltag_ros (x right, y up, z out of the tag) is the package's marker frame.

Both functions return ``{frame_id: [MarkerObservation]}`` (the message header's frame, without a
leading ``/``); :func:`observations_from_message` picks the right one by ``msg._type``.

The bag source (:data:`ros.bag_source.DETECTION_CONVERTERS`) and the relay node
(:mod:`.apriltag_relay`) both convert through these functions.
"""
from __future__ import annotations

import logging
import threading
from typing import Callable, Dict, List, Optional

import numpy as np

from .. import geometry as geo
from ..camera import CameraModel
from ..detections import MarkerObservation
from ..errors import GeometryError, MeasurementError
from ..markers import aruco_corners_from_apriltag, marker_corners

logger = logging.getLogger(__name__)

APRILTAG_MSGS_TYPE = "apriltag_msgs/ApriltagArrayStamped"
APRILTAG_ROS_TYPE = "apriltag_ros/AprilTagDetectionArray"
MESSAGE_TYPES = (APRILTAG_MSGS_TYPE, APRILTAG_ROS_TYPE)


def _frame(header) -> str:
    return str(header.frame_id).lstrip("/")


def apriltag_msgs_to_observations(msg) -> Dict[str, List[MarkerObservation]]:
    """``apriltag_msgs/ApriltagArrayStamped`` -> ``{frame: observations}`` (corners in aruco order).

    Raises:
        MeasurementError: a tag without 4 corners (naming the field).
    """
    out: List[MarkerObservation] = []
    for i, tag in enumerate(msg.apriltags):
        if len(tag.corners) != 4:
            raise MeasurementError(f"apriltags[{i}].corners: expected 4 points, got {len(tag.corners)}")
        px = np.array([[float(c.x), float(c.y)] for c in tag.corners])
        out.append(MarkerObservation(int(tag.id), aruco_corners_from_apriltag(px)))
    return {_frame(msg.header): out}


def apriltag_ros_to_observations(msg, model_for: Callable[[str], Optional[CameraModel]]
                                 ) -> Dict[str, List[MarkerObservation]]:
    """``apriltag_ros/AprilTagDetectionArray`` -> ``{frame: observations}``, corners projected from the poses.

    Args:
        model_for: frame_id -> the camera model to project with (None: that camera is unknown).

    Raises:
        MeasurementError: an unusable pose or size (naming the field), or no model for the frame.
    """
    out: Dict[str, List[MarkerObservation]] = {}
    skipped = 0
    for i, det in enumerate(msg.detections):
        if len(det.id) != 1 or len(det.size) != 1:
            skipped += 1          # a bundle: its pose is the bundle origin's, not a tag's
            continue
        frame = _frame(det.pose.header) or _frame(msg.header)
        model = model_for(frame)
        if model is None:
            raise MeasurementError(f"detections[{i}]: no camera model for frame '{frame}' to project the tag with")
        size = float(det.size[0])
        if not np.isfinite(size) or size <= 0:
            raise MeasurementError(f"detections[{i}].size: expected a positive length, got {size!r}")
        p, q = det.pose.pose.pose.position, det.pose.pose.pose.orientation
        try:
            T_cam_tag = geo.transform_from_translation_quaternion([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
        except GeometryError as exc:
            raise MeasurementError(f"detections[{i}].pose: {exc}") from None
        pts = geo.transform_points(T_cam_tag, marker_corners(size))
        if np.any(pts[:, 2] <= 0):
            raise MeasurementError(f"detections[{i}].pose: the tag is behind the camera")
        out.setdefault(frame, []).append(MarkerObservation(int(det.id[0]), model.project(pts)))
    if skipped:
        logger.debug("apriltag_ros: %d bundle detection(s) skipped", skipped)
    if not out:
        out[_frame(msg.header)] = []
    return out


def observations_from_message(msg, model_for: Optional[Callable[[str], Optional[CameraModel]]] = None
                              ) -> Dict[str, List[MarkerObservation]]:
    """Either message type (by ``msg._type``) -> ``{frame: observations}``.

    Raises:
        MeasurementError: an unknown message type or a bad message.
    """
    kind = getattr(msg, "_type", "")
    if kind == APRILTAG_MSGS_TYPE:
        return apriltag_msgs_to_observations(msg)
    if kind == APRILTAG_ROS_TYPE:
        return apriltag_ros_to_observations(msg, model_for or (lambda _frame: None))
    raise MeasurementError(f"message type {kind!r} is not an AprilTag detection type ({', '.join(MESSAGE_TYPES)})")


def apriltag_ros_definition() -> str:
    """The full definition text of ``apriltag_ros/AprilTagDetectionArray`` (AprilRobotics'), as a
    publisher or a bag carries it: to publish or record such messages without that package."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from std_msgs.msg import Header

    sep = "\n" + "=" * 80 + "\n"
    return sep.join(["std_msgs/Header header\nAprilTagDetection[] detections\n",
                     "MSG: std_msgs/Header\n" + Header._full_text,
                     "MSG: apriltag_ros/AprilTagDetection\nint32[] id\nfloat64[] size\n"
                     "geometry_msgs/PoseWithCovarianceStamped pose\n",
                     "MSG: geometry_msgs/PoseWithCovarianceStamped\n" + PoseWithCovarianceStamped._full_text])


#: genpy's code generator numbers its temporaries with a module-wide counter: two threads generating
#: at once (the relay's first message on two cameras) produce code that uses a name it never set.
_GENPY_LOCK = threading.Lock()


def message_classes(type_name: str, definition: str) -> Dict[str, type]:
    """Every message class of a full definition text (``type_name`` and the types it embeds),
    built as rosbag builds them: no package of that type needs to be installed. Thread-safe."""
    import genpy.dynamic

    with _GENPY_LOCK:
        return genpy.dynamic.generate_dynamic(type_name, definition)


def message_class(type_name: str, definition: str):
    """The message class of ``type_name`` built from its full definition text (:func:`message_classes`)."""
    return message_classes(type_name, definition)[type_name]
